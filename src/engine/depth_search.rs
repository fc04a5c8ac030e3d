//! Depth in the search: the SDF expert's fused term of every scored cell, the translations of
//! the best cells, and a search's answer (docs/DESIGN.md §2, RGB-D fusion).

use rayon::prelude::*;

use super::search::{self, CellProbability, SearchResult, group_modes};
use super::{CameraPoints, Cancel, EngineError, ModelObject, Prediction, cancel};
use crate::so3::modes::{MODE_MASS_FRACTION, MODE_MIN_MASS};
use crate::so3::{GridLevel, to_row_major_f32};

/// The depth points of one image.
#[derive(Debug, Clone, PartialEq)]
pub enum SeenPoints {
    /// Points relative to the object's centre, normalised units, camera frame (`τ = 0`).
    Centred(Vec<nalgebra::Vector3<f32>>),
    /// Points as the camera saw them (from a depth image): the translation is found.
    Camera(CameraPoints),
}

/// Depth of one image for RGB-D fusion: the object the points belong to, and the points.
#[derive(Clone, Copy)]
pub struct DepthInput<'a> {
    /// The object (its SDF expert scores the points).
    pub object: &'a ModelObject,
    /// The points.
    pub points: &'a SeenPoints,
}

impl DepthInput<'_> {
    /// The fused term of every cell centre of `grid` given (row-major rotations):
    /// `κ_L·(−U_SDF)` ([`super::DepthFusion::tempering`]), at `τ = 0` for centred points, at the
    /// estimate `τ₀(R)` for camera points ([`super::fusion`]).
    /// Stops with [`EngineError::Cancelled`] between chunks ([`cancel::cancel_chunk`]) once
    /// `cancel` is set.
    pub fn cell_log_measure(
        &self,
        grid: &GridLevel,
        rotations: &[[f32; 9]],
        cancel: &Cancel,
    ) -> Result<Vec<f32>, EngineError> {
        let kappa = self.object.fusion.tempering(grid);
        let mut terms = Vec::with_capacity(rotations.len());
        let points = match self.points {
            SeenPoints::Centred(p) => p.len(),
            SeenPoints::Camera(p) => p.points.len(),
        };
        for chunk in rotations.chunks(cancel::cancel_chunk(points)) {
            cancel.check()?;
            terms.extend(self.log_measure(chunk).into_iter().map(|t| t * kappa));
        }
        Ok(terms)
    }

    /// The fused term `−U_SDF` of every candidate (row-major rotations): at `τ = 0` for centred
    /// points, at the estimate `τ₀(R)` for camera points ([`super::fusion`]).
    pub fn log_measure(&self, rotations: &[[f32; 9]]) -> Vec<f32> {
        let fusion = &self.object.fusion;
        match self.points {
            SeenPoints::Centred(points) => fusion.log_measure(points, rotations),
            SeenPoints::Camera(points) => fusion.posed_log_measure(points, rotations),
        }
    }

    /// For camera points, the best-fitting translation of rotation `r` (row-major) and the fused
    /// term there ([`super::DepthFusion::fit_translation`]); `None` for centred points.
    pub fn fit(&self, r: &[f32; 9]) -> Option<(nalgebra::Vector3<f32>, f32)> {
        match self.points {
            SeenPoints::Centred(_) => None,
            SeenPoints::Camera(points) => Some(self.object.fusion.fit_translation(points, r)),
        }
    }

    /// `τ` (normalised units, camera frame) as the mesh's translation `t`, with
    /// `x_camera = R·x_mesh + t`: `t = s·τ − R·centre` (`x_object = (x_mesh − centre)/s`).
    pub fn mesh_translation(
        &self,
        r: &nalgebra::Rotation3<f64>,
        tau: &nalgebra::Vector3<f32>,
    ) -> [f64; 3] {
        let n = &self.object.normalisation;
        let t = tau.cast::<f64>() * n.scale - r * nalgebra::Vector3::from(n.centre);
        [t.x, t.y, t.z]
    }
}

/// How far below the best cell's fused term a cell of a full distribution still gets its term
/// from its children ([`cell_means`]); below, its mass is negligible either way.
pub(super) const CELL_MEAN_RANGE: f32 = 30.0;

/// Replaces the fused term of the cells of `grid` within [`CELL_MEAN_RANGE`] of the best by
/// `log mean_k exp(term(child_k))` over their 8 children (each scored at `children`'s level):
/// the cell's share of the depth factor's mass, where a centre alone misses a peak narrower than
/// the cell.
pub(super) fn cell_means(
    depth: &DepthInput<'_>,
    grid: &GridLevel,
    children: &GridLevel,
    terms: &mut [f32],
    cancel: &Cancel,
) -> Result<(), EngineError> {
    let best = terms.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let near: Vec<usize> = (0..terms.len())
        .filter(|&i| terms[i] >= best - CELL_MEAN_RANGE)
        .collect();
    let rotations: Vec<[f32; 9]> = near
        .iter()
        .flat_map(|&i| grid.children(i as u64))
        .map(|c| to_row_major_f32(&children.rotation(c)))
        .collect();
    let child_terms = depth.cell_log_measure(children, &rotations, cancel)?;
    for (&i, eight) in near.iter().zip(child_terms.chunks_exact(8)) {
        terms[i] = search::log_sum_exp(eight) as f32 - 8f32.ln();
    }
    Ok(())
}

/// The depth side of a batch of coarse-to-fine searches: each image's fused term added at every
/// level, from a quarter of the camera points above the finest level; at the finest, the best
/// cells' translations fitted ([`refit_best`]) and kept for the answer.
pub(super) struct DepthSearch<'a> {
    depth: &'a [Option<DepthInput<'a>>],
    coarse: Vec<Option<SeenPoints>>,
    finest: u8,
    refits: usize,
    pub(super) fitted: Vec<Vec<(u64, nalgebra::Vector3<f32>)>>,
}

impl<'a> DepthSearch<'a> {
    pub(super) fn new(depth: &'a [Option<DepthInput<'a>>], finest: u8, refits: usize) -> Self {
        let coarse = depth
            .iter()
            .map(|d| match d.map(|d| d.points) {
                Some(SeenPoints::Camera(p)) => Some(SeenPoints::Camera(p.subsample(COARSE_POINTS))),
                _ => None,
            })
            .collect();
        DepthSearch {
            depth,
            coarse,
            finest,
            refits,
            fitted: vec![Vec::new(); depth.len()],
        }
    }

    /// Adds the fused term of each image with depth to its `logits` of `grid`'s `cells`
    /// (`mats`: their rotations, or empty to compute them here).
    pub(super) fn add_terms(
        &mut self,
        grid: &GridLevel,
        cells: &[Vec<u64>],
        mats: &[Vec<[f32; 9]>],
        logits: &mut [Vec<f32>],
        cancel: &Cancel,
    ) -> Result<(), EngineError> {
        for (i, d) in self.depth.iter().enumerate() {
            let Some(d) = d else { continue };
            let own;
            let m: &[[f32; 9]] = match mats.get(i) {
                Some(m) => m,
                None => {
                    own = cells[i]
                        .iter()
                        .map(|&c| to_row_major_f32(&grid.rotation(c)))
                        .collect::<Vec<_>>();
                    &own
                }
            };
            let finest = grid.level() == self.finest;
            let fused = match (&self.coarse[i], finest) {
                (Some(points), false) => {
                    DepthInput { points, ..*d }.cell_log_measure(grid, m, cancel)?
                }
                _ => d.cell_log_measure(grid, m, cancel)?,
            };
            if finest {
                let kappa = d.object.fusion.tempering(grid);
                self.fitted[i] =
                    refit_best(d, m, &cells[i], &mut logits[i], &fused, self.refits, kappa);
            }
            for (l, d) in logits[i].iter_mut().zip(&fused) {
                *l += d;
            }
        }
        Ok(())
    }
}

/// A search's answer: the top-k cells of its finest level, their rotations, the modes, and with
/// camera points the translation of each top cell (the fitted ones reused, the others fitted).
pub(super) fn prediction_of(
    grid: &GridLevel,
    result: SearchResult,
    top_k: usize,
    mode_angle: f64,
    depth: Option<&DepthInput<'_>>,
    fitted: &[(u64, nalgebra::Vector3<f32>)],
) -> Prediction {
    let modes = group_modes(
        grid,
        &result.cells,
        mode_angle,
        MODE_MASS_FRACTION,
        MODE_MIN_MASS,
    );
    let top: Vec<CellProbability> = result.cells[..top_k.min(result.cells.len())].to_vec();
    let rotations: Vec<_> = top.iter().map(|c| grid.rotation(c.cell)).collect();
    let translations = match depth {
        Some(d) if matches!(d.points, SeenPoints::Camera(_)) => top
            .iter()
            .zip(&rotations)
            .map(|(c, r)| {
                let tau = match fitted.iter().find(|(cell, _)| *cell == c.cell) {
                    Some((_, tau)) => *tau,
                    None => d
                        .fit(&to_row_major_f32(r))
                        .map_or_else(nalgebra::Vector3::zeros, |(tau, _)| tau),
                };
                d.mesh_translation(r, &tau)
            })
            .collect(),
        _ => Vec::new(),
    };
    Prediction {
        rotations: rotations.iter().map(crate::so3::to_quaternion).collect(),
        top,
        modes,
        covered_mass: result.covered_mass,
        translations,
    }
}

/// Fewest cells of a search's finest level whose translation is fitted, with camera depth points.
pub(super) const MIN_REFITS: usize = 16;

/// Camera depth points scored at the levels of a search above its finest (which scores all).
pub(super) const COARSE_POINTS: usize = 64;

/// With camera points, fits the translation of the `n` best cells of a search's finest level (by
/// image log-weight plus the fused term at `τ₀`), so that their total is the image's plus the
/// fitted term (tempered by `kappa`, as `fused`); returns the fitted translations by cell.
/// Nothing for centred points.
pub(super) fn refit_best(
    depth: &DepthInput<'_>,
    rotations: &[[f32; 9]],
    cells: &[u64],
    logits: &mut [f32],
    fused: &[f32],
    n: usize,
    kappa: f32,
) -> Vec<(u64, nalgebra::Vector3<f32>)> {
    if !matches!(depth.points, SeenPoints::Camera(_)) {
        return Vec::new();
    }
    let total: Vec<f64> = logits
        .iter()
        .zip(fused)
        .map(|(l, f)| (l + f) as f64)
        .collect();
    let best = search::top_indices(&total, n);
    let fits: Vec<(usize, nalgebra::Vector3<f32>, f32)> = best
        .par_iter()
        .filter_map(|&j| depth.fit(&rotations[j]).map(|(tau, term)| (j, tau, term)))
        .collect();
    fits.into_iter()
        .map(|(j, tau, term)| {
            // `logits` gets the difference, so that `logits + fused` is the fitted total.
            logits[j] += kappa * term - fused[j];
            (cells[j], tau)
        })
        .collect()
}
