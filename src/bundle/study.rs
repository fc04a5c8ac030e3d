//! The search study a bundle may carry (`search-study.json`, written by `alignist-train bench
//! --write-study`): for each coarse-to-fine search studied, how often its top-1 agreed with the
//! exhaustive argmax of the finest level on held-out renders. Agreement is the model's, not the
//! CPU's: a server's calibration reads it to know which searches it may choose, and times them on
//! its own CPU.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::BundleError;
use crate::net::Precision;

/// The keep tapers a search accepts: from an eighth to eight times as many cells per finer
/// level (the engine re-exports it as `KEEP_TAPER`).
pub const KEEP_TAPER: std::ops::RangeInclusive<f64> = 0.125..=8.0;

/// The study's file in a bundle folder.
pub const SEARCH_STUDY_FILE: &str = "search-study.json";

/// One studied search and what it scored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StudiedSearch {
    /// Level scored in full first.
    pub start_level: u8,
    /// Most cells kept at the first refinement.
    pub keep: usize,
    /// Keep the cells holding this fraction of a level's mass (at most `keep`).
    pub keep_mass: Option<f64>,
    /// Each finer level keeps this many times as many cells.
    pub keep_taper: f64,
    /// Arithmetic of the levels before the finest (`f32`, `bf16`, `f16`, `i8`).
    pub coarse_precision: String,
    /// Whether the finest level was scored in the coarse precision too, its best cells then
    /// rescored in f32 (absent in studies written before the option: `false`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub rescore_finest: bool,
    /// The levels up to this one (below the study's level) were ranked by the shape branch
    /// alone (absent: every level by both branches, as in studies written before the option).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shape_only_to: Option<u8>,
    /// Fraction of images whose top-1 is the exhaustive argmax's cell or a neighbour.
    pub agreement: f64,
    /// Fraction of images whose top-1 scores within 0.01 of the exhaustive maximum.
    pub found_maximum: f64,
}

/// A bundle's search study.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SearchStudy {
    /// The finest level, scored exhaustively for the reference argmax.
    pub level: u8,
    /// Held-out images studied.
    pub images: usize,
    /// The command that wrote the study.
    pub command: String,
    /// The seed its images were rendered from (`alignist-train bench`'s study seed), so that a
    /// check of the served search can draw images the study did not see. Absent in studies
    /// written before the field (their images came from the bench's own seed, 99).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    /// Every search studied.
    pub searches: Vec<StudiedSearch>,
    /// The sha256 of the network the study measured (the manifest's entry for
    /// `network.safetensors`), so that searches are added to it only for the same weights.
    /// Absent in studies written before the field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub network_sha256: Option<String>,
    /// Each studied image's exhaustive argmax, in the order the images were rendered, so that
    /// searches can be added to the study (`bench --extend-study`) without scoring every cell of
    /// the finest level again. Empty in studies written before the field.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub references: Vec<StudyReference>,
    /// The commands that added searches to the study after it was written.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub extended_by: Vec<String>,
}

/// The exhaustive argmax of one image at a study's level: what each search's top-1 is compared
/// with.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Argmax {
    /// The cell of the study's level with the highest log-weight.
    pub cell: u64,
    /// Its log-weight `s_θ + s_φ` in f32.
    pub logit: f32,
}

/// One studied image's [`Argmax`], with the image it is of.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StudyReference {
    /// The sha256 of the image's RGB bytes: a reference is used only for the same image.
    pub image_sha256: String,
    /// The image's argmax (its fields `cell` and `logit` sit beside `image_sha256` in the file).
    #[serde(flatten)]
    pub argmax: Argmax,
}

impl StudiedSearch {
    /// The coarse precision, parsed.
    pub fn precision(&self) -> Result<Precision, String> {
        self.coarse_precision.parse()
    }
}

impl SearchStudy {
    /// The study in `folder`, `None` when the bundle has none; an unreadable or out-of-range
    /// one is an error naming the file and the field.
    pub fn load(folder: &Path) -> Result<Option<SearchStudy>, BundleError> {
        let path = folder.join(SEARCH_STUDY_FILE);
        let shown = path.display().to_string();
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => {
                return Err(BundleError::Io {
                    path: shown,
                    source,
                });
            }
        };
        let study: SearchStudy =
            serde_json::from_str(&text).map_err(|source| BundleError::Json {
                path: shown.clone(),
                source,
            })?;
        study.check().map_err(|message| BundleError::Manifest {
            path: shown,
            message,
        })?;
        Ok(Some(study))
    }

    /// Writes the study into `folder`.
    pub fn save(&self, folder: &Path) -> Result<(), BundleError> {
        let path = folder.join(SEARCH_STUDY_FILE);
        let text = serde_json::to_string_pretty(self).map_err(|source| BundleError::Json {
            path: path.display().to_string(),
            source,
        })?;
        std::fs::write(&path, text + "\n").map_err(|source| BundleError::Io {
            path: path.display().to_string(),
            source,
        })
    }

    /// The values' ranges, naming the field of the first one out of range.
    fn check(&self) -> Result<(), String> {
        if self.images == 0 {
            return Err("images: must be positive".into());
        }
        if !self.references.is_empty() && self.references.len() != self.images {
            return Err(format!(
                "references: {} of them for {} images (one per image, or none)",
                self.references.len(),
                self.images
            ));
        }
        // `72·8^L` cells at level L (`so3::GridLevel::len`).
        let cells = 72u64 << (3 * u32::from(self.level.min(crate::so3::grid::MAX_LEVEL)));
        for (i, r) in self.references.iter().map(|r| r.argmax).enumerate() {
            if r.cell >= cells {
                return Err(format!(
                    "references[{i}].cell: {} is not a cell of level {} ({cells} cells)",
                    r.cell, self.level
                ));
            }
            if !r.logit.is_finite() {
                return Err(format!("references[{i}].logit: {} is not finite", r.logit));
            }
        }
        for (i, s) in self.searches.iter().enumerate() {
            let field = |name: &str| format!("searches[{i}].{name}");
            if s.start_level >= self.level {
                return Err(format!(
                    "{}: {} must be below the study's level {}",
                    field("start_level"),
                    s.start_level,
                    self.level
                ));
            }
            if s.keep == 0 {
                return Err(format!("{}: must be positive", field("keep")));
            }
            if let Some(to) = s.shape_only_to
                && !(s.start_level..self.level).contains(&to)
            {
                return Err(format!(
                    "{}: {to} must be from the start level {} to below the study's level {}",
                    field("shape_only_to"),
                    s.start_level,
                    self.level
                ));
            }
            if let Some(m) = s.keep_mass
                && !(m > 0.0 && m <= 1.0)
            {
                return Err(format!("{}: {m} must be in (0, 1]", field("keep_mass")));
            }
            if !KEEP_TAPER.contains(&s.keep_taper) {
                return Err(format!(
                    "{}: {} must be in {:?}",
                    field("keep_taper"),
                    s.keep_taper,
                    KEEP_TAPER
                ));
            }
            s.precision()
                .map_err(|e| format!("{}: {e}", field("coarse_precision")))?;
            for (name, v) in [
                ("agreement", s.agreement),
                ("found_maximum", s.found_maximum),
            ] {
                if !(0.0..=1.0).contains(&v) {
                    return Err(format!("{}: {v} must be in [0, 1]", field(name)));
                }
            }
        }
        Ok(())
    }
}
