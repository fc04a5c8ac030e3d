//! How the engine serves: levels, the coarse-to-fine search, request limits (docs/DESIGN.md §2,
//! "Inference").

use super::{EngineError, ImageLimits, invalid};
use crate::net::{Branches, Precision};
use crate::so3::MAX_LEVEL;

/// Most rotations one Predict may return (the search keeps `top_k / 8` cells per level, so this
/// also bounds its work).
pub const MAX_TOP_K: usize = 16_384;

/// The keep tapers a search accepts ([`SearchParams::keep_taper`]): from an eighth to eight times
/// as many cells per finer level.
pub use crate::bundle::study::KEEP_TAPER;

/// How the engine serves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EngineConfig {
    /// Highest level served in full (its rotation projections are precomputed at load).
    pub max_full_level: u8,
    /// Default finest level of the search.
    pub search_default_level: u8,
    /// Highest level a search may reach.
    pub search_max_level: u8,
    /// The coarse-to-fine search: its start level, the cells it keeps per level and the
    /// arithmetic of its coarse levels.
    pub search: SearchParams,
    /// Limits on request images.
    pub image_limits: ImageLimits,
    /// Most depth points per request.
    pub max_depth_points: usize,
    /// Depth pixels of a depth image used per detection (evenly spaced in the box).
    pub depth_image_points: usize,
    /// With `Some(ms)`, the search is chosen at load on this CPU ([`super::calibrate`]) among the
    /// bundle's studied searches: the most agreeing one predicted within `ms` (agreements one
    /// studied image apart count as equal; among equals the fastest); with `None`, the
    /// search above is served as it is.
    pub search_budget_ms: Option<f64>,
    /// The agreement with the exhaustive argmax a calibrated search must have reached in the
    /// bundle's study.
    pub search_agreement: f64,
    /// The widest head kernels the model may use.
    pub kernels: crate::net::Kernels,
}

/// How a coarse-to-fine search runs: the level it scores in full, and the cells it refines.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SearchParams {
    /// Level scored in full first.
    pub start_level: u8,
    /// Most cells kept per level.
    pub keep: usize,
    /// Keep the cells holding this fraction of each level's mass, at most `keep` (`None`:
    /// always `keep`).
    pub keep_mass: Option<f64>,
    /// Each finer level keeps `keep_taper` times as many cells as the one before (1: `keep` at
    /// every level).
    pub keep_taper: f64,
    /// The arithmetic of every level but the finest, which is scored in f32 (or rescored in it,
    /// `rescore_finest`): bfloat16 ranks
    /// the cells to refine at about 2.6 times the f32 rate on AMD Zen 4, f16 at 1.8–1.9 times
    /// and 8-bit integers at about 3 times on an Intel Xeon with AVX-512 FP16 and VNNI.
    pub coarse_precision: Precision,
    /// Score the finest level in `coarse_precision` too, then its [`RESCORED_CELLS`] most
    /// probable cells (at least the top-k) again in f32: the finest level's rows at the coarse
    /// rate, the answer's cells at f32's. No effect with f32 coarse levels, or where the finest
    /// level is the start level (scored in f32 from its projections).
    pub rescore_finest: bool,
    /// Rank the cells of the levels up to this one (never the finest, whose scores are
    /// answered) by the shape branch `s_θ` alone, at about half the arithmetic of a row
    /// ([`Branches::Shape`]); `None`: every level by `s_θ + s_φ`. Both branches learn the same
    /// symmetric modes, so `s_θ` alone keeps the cells holding the combined maximum (measured in
    /// the bundle's search study like any other search).
    pub shape_only_to: Option<u8>,
}

/// Cells of the finest level scored again in f32 by a search with
/// [`SearchParams::rescore_finest`] (the top-k, where larger): 64 of the 2 048 cells a keep of
/// 256 expands, far more than the cells that i8's or bfloat16's few-% score errors can reorder
/// around the maximum.
pub const RESCORED_CELLS: usize = 64;

impl SearchParams {
    /// Whether a search from `start` to `finest` rescores its finest level: asked for, in a
    /// reduced precision, and the finest level is not the start level (scored from its
    /// projections, which carry no rotations to rescore).
    pub fn rescores_to(&self, start: u8, finest: u8) -> bool {
        finest > start && self.rescores()
    }

    /// The arithmetic of level `l`'s rows in a search from `start` to `finest` (before any
    /// rescoring): f32 at the finest level unless it is rescored, the coarse precision above it.
    pub fn precision_at(&self, l: u8, start: u8, finest: u8) -> Precision {
        if l == finest && !self.rescores_to(start, finest) {
            Precision::F32
        } else {
            self.coarse_precision
        }
    }

    /// The branches that score level `l`'s rows in a search to `finest`: the shape branch alone
    /// up to [`SearchParams::shape_only_to`], both at the finest level and below that one.
    pub fn branches_at(&self, l: u8, finest: u8) -> Branches {
        match self.shape_only_to {
            Some(to) if l <= to && l < finest => Branches::Shape,
            _ => Branches::Both,
        }
    }

    /// Whether the finest level is scored in the coarse precision and its best cells rescored
    /// (a rescoring flag with f32 coarse levels changes nothing).
    pub fn rescores(&self) -> bool {
        self.rescore_finest && self.coarse_precision != Precision::F32
    }
}

impl SearchParams {
    /// The search a study's entry measured (`None` when its precision does not parse).
    pub fn of_studied(s: &crate::bundle::study::StudiedSearch) -> Option<SearchParams> {
        Some(SearchParams {
            start_level: s.start_level,
            keep: s.keep,
            keep_mass: s.keep_mass,
            keep_taper: s.keep_taper,
            coarse_precision: s.precision().ok()?,
            rescore_finest: s.rescore_finest,
            shape_only_to: s.shape_only_to,
        })
    }

    /// Start at `start_level`, keep `keep` cells at the first refinement and half as many at
    /// each finer one, the coarse levels in `coarse_precision` and by both branches, the finest
    /// in f32.
    pub fn halving(start_level: u8, keep: usize, coarse_precision: Precision) -> SearchParams {
        SearchParams {
            start_level,
            keep,
            keep_mass: None,
            keep_taper: 0.5,
            coarse_precision,
            rescore_finest: false,
            shape_only_to: None,
        }
    }

    /// The cells it keeps, in words: `128`, `0.99 mass ≤512`, `512 ×0.5/level`.
    pub fn keep_description(&self) -> String {
        let mut keep = match self.keep_mass {
            Some(m) => format!("{m} mass ≤{}", self.keep),
            None => self.keep.to_string(),
        };
        if self.keep_taper != 1.0 {
            keep += &format!(" ×{}/level", self.keep_taper);
        }
        keep
    }
}

impl std::fmt::Display for SearchParams {
    /// `start 2, keep 1024 ×0.5/level, coarse bf16` (a keep by mass: `keep 0.999 mass ≤512`;
    /// rescoring the finest level: `…, coarse i8, finest i8 rescored`; ranking by the shape
    /// branch: `…, shape branch to level 3`).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "start {}, keep {}, coarse {}",
            self.start_level,
            self.keep_description(),
            self.coarse_precision
        )?;
        if self.rescores() {
            write!(f, ", finest {} rescored", self.coarse_precision)?;
        }
        if let Some(to) = self.shape_only_to {
            write!(f, ", shape branch to level {to}")?;
        }
        Ok(())
    }
}

impl EngineConfig {
    /// As `alignist-server` serves with its default flags: this configuration with the search
    /// calibrated on this CPU within [`super::calibrate::DEFAULT_SEARCH_BUDGET_MS`].
    pub fn served() -> Self {
        Self {
            search_budget_ms: Some(super::calibrate::DEFAULT_SEARCH_BUDGET_MS),
            ..Self::default()
        }
    }

    /// The levels a bundle is served at: this configuration's, capped by the levels its
    /// manifest sets (a cap its shipper chose; the trainer sets none).
    pub fn within(&self, levels: &crate::bundle::model::GridLevels) -> EngineConfig {
        EngineConfig {
            max_full_level: self.max_full_level.min(levels.full_max),
            search: SearchParams {
                start_level: self.search.start_level.min(levels.full_max),
                ..self.search
            },
            search_default_level: self.search_default_level.min(levels.search_max),
            search_max_level: self.search_max_level.min(levels.search_max),
            ..*self
        }
    }

    /// The search this configuration runs.
    pub fn search(&self) -> SearchParams {
        self.search
    }

    /// Checks the levels against each other and the grid, and the limits: a server must not
    /// start with settings that make every default call fail.
    pub fn validate(&self) -> Result<(), EngineError> {
        let bad = |field: &str, message: String| Err(invalid(field, message));
        if self.max_full_level > MAX_LEVEL {
            return bad(
                "max_full_level",
                format!(
                    "{} is above the grid's highest level {MAX_LEVEL}",
                    self.max_full_level
                ),
            );
        }
        if self.search_max_level > MAX_LEVEL {
            return bad(
                "search_max_level",
                format!(
                    "{} is above the grid's highest level {MAX_LEVEL}",
                    self.search_max_level
                ),
            );
        }
        if self.search.start_level > self.search_default_level
            || self.search_default_level > self.search_max_level
        {
            return bad(
                "search levels",
                format!(
                    "need start ({}) ≤ default ({}) ≤ maximum ({})",
                    self.search.start_level, self.search_default_level, self.search_max_level
                ),
            );
        }
        if self.search.start_level > self.max_full_level {
            return bad(
                "search_start_level",
                format!(
                    "{} is above the highest full level {} (the search starts from a full level)",
                    self.search.start_level, self.max_full_level
                ),
            );
        }
        if let Some(f) = self.search.keep_mass
            && !(f > 0.0 && f <= 1.0)
        {
            return bad("keep_mass", format!("{f} must be in (0, 1]"));
        }
        if !KEEP_TAPER.contains(&self.search.keep_taper) {
            return bad(
                "keep_taper",
                format!("{} must be in {KEEP_TAPER:?}", self.search.keep_taper),
            );
        }
        if self.search.keep == 0
            || self.image_limits.max_bytes == 0
            || self.image_limits.max_pixels == 0
        {
            return bad(
                "limits",
                "keep and the image limits must be positive".into(),
            );
        }
        if !(1..=self.max_depth_points).contains(&self.depth_image_points) {
            return bad(
                "depth_image_points",
                format!(
                    "{} must be in 1 ..= {} (max_depth_points)",
                    self.depth_image_points, self.max_depth_points
                ),
            );
        }
        Ok(())
    }
}

impl Default for EngineConfig {
    fn default() -> Self {
        Self {
            max_full_level: 4,
            search_default_level: 5,
            search_max_level: 6,
            // Chosen by the search study of `alignist-train bench` (held-out renders, top-10 to
            // level 5, against the exhaustive level-5 argmax; docs/BENCHMARKS.md): with the
            // coarse levels in bfloat16, 1024 cells halving per level (1024, 512, 256) agreed on
            // 189 of 190 distinct images over the bench's sets of 150 and 50, at p50 ~22 ms;
            // 768 halving, ~4 ms faster, on 188 (98.9 %). The search before, 128 at every level in
            // f32, agreed on 93–94 %.
            search: SearchParams {
                start_level: 2,
                keep: 1024,
                keep_mass: None,
                keep_taper: 0.5,
                coarse_precision: Precision::Bf16,
                rescore_finest: false,
                shape_only_to: None,
            },
            image_limits: ImageLimits::default(),
            max_depth_points: 10_000,
            depth_image_points: 256,
            search_budget_ms: None,
            search_agreement: 0.99,
            kernels: crate::net::Kernels::from_env(),
        }
    }
}
