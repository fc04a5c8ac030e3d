//! RGB-D fusion (beyond the paper): object points seen by a depth camera are scored by the
//! object's SDF expert on the candidate rotations and multiplied into the image's distribution
//! (a product of experts, like the paper's training targets).
//!
//! For a candidate `R` and the object's centre `τ` in the camera frame, the points `q_i` sit at
//! `x_i = Rᵀ·(q_i − τ)` in the object's frame; the fused term is `−U_SDF(R, τ)` on those points,
//! with the λ, ε and norm the expert set was selected with (docs/DESIGN.md §2).
//!
//! Points relative to the object's centre (the old input) have `τ = 0`. Points as the camera sees
//! them ([`CameraPoints`], from a depth image) have `τ` found, not given:
//! - for every candidate, `τ₀(R) = c − R·v(Rᵀ·τ̂, ‖τ‖)`: the points' centroid `c` less the rotated
//!   centroid `v` of the object's surface seen from the view direction `Rᵀ·τ̂` at the distance
//!   `‖τ‖` ([`ViewTable`], rendered from the mesh at load at five distances); both centroids
//!   weigh each pixel by `z²`, so that pixels count as surface area seen head-on;
//! - for the best candidates of a search's finest level, a few Gauss–Newton steps on
//!   `Σ f_SDF(x_i)²` ([`DepthFusion::fit_translation`]), so that a rotation's fused score is its
//!   best fit over translation, and the top rotations come with their translation.

use std::sync::OnceLock;

use nalgebra::{Matrix3, Rotation3, Vector3};
use rayon::prelude::*;

use super::EngineError;
use super::depth::BackProjected;
use crate::bundle::experts::ExpertSet;
use crate::cad::{Camera, Mesh, Pose, RenderOptions, render};
use crate::experts::baked::VoxelGrid;
use crate::experts::energy::{EnergyParams, sdf_energy};
use crate::experts::run_batched;

/// HEALPix depth of the view directions of a [`ViewTable`] (3 072 directions, ~3.7° apart; looked up
/// with bilinear interpolation).
const VIEW_DEPTH: u8 = 4;

/// Gauss–Newton steps of [`DepthFusion::fit_translation`].
const FIT_STEPS: usize = 6;

/// Camera distances (object radii, centre to camera) of a [`ViewTable`]'s layers, far to near:
/// evenly spaced in `1/D` from 0.05 to 0.5, the nearest a request can be (its points' centroid
/// must lie ≥ 1 radius in front of the camera). Up close a camera sees less of the object than
/// from afar (a sphere at 3 radii shows a cap of 70.5°, not a hemisphere), and the seen surface's
/// centroid moves towards it by up to a tenth of the radius: a far table alone put `τ₀` off by
/// 8–10 % of the radius on cylinders seen from 2.7–3.6 radii.
const VIEW_INVERSE_DISTANCES: [f64; 5] = [0.05, 0.1625, 0.275, 0.3875, 0.5];

/// The centroid of the surface a camera sees, per view direction and camera distance, in the
/// object's frame.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewTable {
    /// Per layer of [`VIEW_INVERSE_DISTANCES`], per HEALPix direction.
    layers: Vec<Vec<Vector3<f32>>>,
}

impl ViewTable {
    /// Renders `mesh` (normalised) from every HEALPix direction of [`VIEW_DEPTH`] at every
    /// distance of [`VIEW_INVERSE_DISTANCES`], and averages the object coordinates of the pixels
    /// it covers, each weighted by its depth² (its surface area seen head-on, as
    /// [`CameraPoints::centroid`] weighs the camera's points): 15 360 renders of 32², ~2 s per
    /// object on 2 cores (`cargo run --release --example probe_fusion -- --table-time`).
    pub fn build(mesh: &Mesh) -> ViewTable {
        let size = 32u32;
        let n = cdshealpix::nested::n_hash(VIEW_DEPTH);
        let layers = VIEW_INVERSE_DISTANCES
            .iter()
            .map(|&u| {
                let distance = 1.0 / u;
                // The bounding sphere's silhouette fills 0.9 of the image.
                let focal = 0.45 * size as f64 * (distance * distance - 1.0).sqrt();
                let camera = Camera::square_with_focal(size, focal);
                (0..n)
                    .into_par_iter()
                    .map(|h| {
                        let d = direction(cdshealpix::nested::center(VIEW_DEPTH, h));
                        let pose = Pose {
                            rotation: looking_along(&d),
                            translation: Vector3::new(0.0, 0.0, distance),
                        };
                        let r = render(mesh, &camera, &pose, &RenderOptions::default());
                        let (mut sum, mut weight) = (Vector3::zeros(), 0f64);
                        for ((seen, p), z) in r.mask.iter().zip(&r.nocs).zip(&r.depth) {
                            if *seen {
                                let w = (*z as f64).powi(2);
                                sum += Vector3::new(p[0], p[1], p[2]).cast::<f64>() * w;
                                weight += w;
                            }
                        }
                        (sum / weight.max(f64::MIN_POSITIVE)).cast()
                    })
                    .collect()
            })
            .collect();
        ViewTable { layers }
    }

    /// The seen surface's centroid for the view direction `d` (object frame, unit, from the camera
    /// towards the object) from `distance` radii: bilinear over directions, linear in `1/D`
    /// between layers (clamped to the table's range).
    pub fn centroid(&self, d: &Vector3<f64>, distance: f64) -> Vector3<f32> {
        let lon = d.y.atan2(d.x);
        let lat = d.z.clamp(-1.0, 1.0).asin();
        let lon = if lon < 0.0 {
            lon + std::f64::consts::TAU
        } else {
            lon
        };
        let last = VIEW_INVERSE_DISTANCES.len() - 1;
        let (u0, u1) = (VIEW_INVERSE_DISTANCES[0], VIEW_INVERSE_DISTANCES[last]);
        let at = ((1.0 / distance).clamp(u0, u1) - u0) / (u1 - u0) * last as f64;
        let below = (at.floor() as usize).min(last - 1);
        let frac = (at - below as f64) as f32;
        cdshealpix::nested::bilinear_interpolation(VIEW_DEPTH, lon, lat)
            .iter()
            .map(|&(h, w)| {
                let h = h as usize;
                (self.layers[below][h] * (1.0 - frac) + self.layers[below + 1][h] * frac) * w as f32
            })
            .sum()
    }

    /// The translation estimate `τ₀(R) = c − R·v(Rᵀ·τ̂, ‖τ‖)` for camera points seen at rotation
    /// `r` (module doc), found in two passes: first looking from the camera towards the points'
    /// centroid `c` at its distance, then towards the first estimate at its distance.
    pub fn initial_translation(&self, points: &CameraPoints, r: &Matrix3<f32>) -> Vector3<f32> {
        let c = points.centroid;
        let seen_from = |t: &Vector3<f32>| {
            let view = (r.transpose() * t.normalize()).cast::<f64>();
            c - r * self.centroid(&view, t.norm() as f64)
        };
        seen_from(&seen_from(&c))
    }
}

fn direction((lon, lat): (f64, f64)) -> Vector3<f64> {
    Vector3::new(lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin())
}

/// A rotation `R` with `R·d = ẑ`: a camera looking along `d` (object frame).
fn looking_along(d: &Vector3<f64>) -> Rotation3<f64> {
    let z = d.normalize();
    let helper = if z.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let x = helper.cross(&z).normalize();
    let y = z.cross(&x);
    Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[
        x.transpose(),
        y.transpose(),
        z.transpose(),
    ]))
}

/// `κ = s²/(s² + h²/12)` for a selection width of `width_deg` and cells of volume `cell_volume`
/// (π²-normalised measure; side `h = 2·volume^⅓` in rotation angle): [`DepthFusion::tempering`].
pub fn cell_tempering(width_deg: f64, cell_volume: f64) -> f32 {
    let w = width_deg.to_radians();
    let s2 = 2.0 * w * w;
    let h = 2.0 * cell_volume.cbrt();
    (s2 / (s2 + h * h / 12.0)) as f32
}

/// Points a depth camera saw on the object, in the object's normalised units, in the frame of the
/// camera that the candidate rotations are given in.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraPoints {
    /// The points.
    pub points: Vec<Vector3<f32>>,
    /// The centroid of all the object's valid depth pixels (not only of `points`), each weighed
    /// by `z²` ([`super::BackProjected::centroid`]).
    pub centroid: Vector3<f32>,
}

impl CameraPoints {
    /// At most `n` of the points, evenly spaced, with the same centroid (so the same `τ₀`).
    pub fn subsample(&self, n: usize) -> CameraPoints {
        let total = self.points.len();
        let n = n.clamp(1, total.max(1)).min(total);
        CameraPoints {
            points: (0..n).map(|i| self.points[i * total / n]).collect(),
            centroid: self.centroid,
        }
    }

    /// The same points in a frame turned by `r` (`q' = r·q`).
    pub fn turned(&self, r: &Rotation3<f32>) -> CameraPoints {
        CameraPoints {
            points: self.points.iter().map(|p| r * p).collect(),
            centroid: r * self.centroid,
        }
    }
}

/// The SDF expert of one object, baked once ([`DepthFusion::warm`], which model loading runs, or
/// on first use), and the view table of its mesh.
pub struct DepthFusion {
    set: ExpertSet,
    baked: OnceLock<(VoxelGrid, ViewTable)>,
}

impl DepthFusion {
    /// Wraps an object's expert set.
    pub fn new(set: ExpertSet) -> Self {
        Self {
            set,
            baked: OnceLock::new(),
        }
    }

    /// The energy parameters of the expert set.
    pub fn params(&self) -> &EnergyParams {
        &self.set.manifest.energy
    }

    /// The expert set.
    pub fn experts(&self) -> &ExpertSet {
        &self.set
    }

    /// Bakes the SDF grid now if it is not baked yet (so that no request pays for it).
    pub fn warm(&self) {
        let _ = self.sdf();
    }

    /// Whether the SDF grid is baked.
    pub fn is_warm(&self) -> bool {
        self.baked.get().is_some()
    }

    fn baked(&self) -> &(VoxelGrid, ViewTable) {
        self.baked.get_or_init(|| {
            let device = crate::backend::device();
            let bake = &self.set.manifest.bake;
            let (grid, table) = rayon::join(
                || {
                    VoxelGrid::bake(bake.resolution, bake.bound, 1, |p| {
                        run_batched(&self.set.sdf, p, 1, &device)
                    })
                },
                || ViewTable::build(&self.set.mesh),
            );
            (grid, table)
        })
    }

    fn sdf(&self) -> &VoxelGrid {
        &self.baked().0
    }

    /// Parses flattened camera-frame `xyz` (in the source mesh's units, relative to the object's
    /// centre) into normalised object units.
    pub fn parse_points(
        &self,
        xyz: &[f32],
        max_points: usize,
    ) -> Result<Vec<Vector3<f32>>, EngineError> {
        let field = "depth.xyz";
        let invalid = |message: String| EngineError::InvalidArgument {
            field: field.into(),
            message,
        };
        if xyz.is_empty() {
            return Err(invalid("has no points".into()));
        }
        if !xyz.len().is_multiple_of(3) {
            return Err(invalid(format!(
                "has {} values, not a multiple of 3 (x, y, z triples)",
                xyz.len()
            )));
        }
        let n = xyz.len() / 3;
        if n > max_points {
            return Err(EngineError::ResourceExhausted {
                field: field.into(),
                message: format!("{n} points is over the limit of {max_points}"),
            });
        }
        if let Some(i) = xyz.iter().position(|v| !v.is_finite()) {
            return Err(invalid(format!("value {i} is not finite")));
        }
        let scale = self.set.manifest.object.normalisation.scale as f32;
        let points: Vec<Vector3<f32>> = xyz
            .chunks_exact(3)
            .map(|c| Vector3::new(c[0], c[1], c[2]) / scale)
            .collect();
        let bound = self.set.manifest.bake.bound * 4.0;
        if let Some(i) = points.iter().position(|p| p.norm() > bound) {
            return Err(invalid(format!(
                "point {i} is {:.2} object radii from the centre; points must be relative to the \
                 object's centre, in the units of its mesh",
                points[i].norm()
            )));
        }
        Ok(points)
    }

    /// `−U_SDF(R)` of the points for every candidate (row-major rotations).
    pub fn log_measure(&self, points: &[Vector3<f32>], rotations: &[[f32; 9]]) -> Vec<f32> {
        let sdf = self.sdf();
        let params = self.params();
        rotations
            .par_iter()
            .map_init(
                || vec![0f32; points.len()],
                |buf, m| {
                    let rt = Matrix3::from_row_slice(m).transpose();
                    for (v, p) in buf.iter_mut().zip(points) {
                        let mut out = [0f32];
                        sdf.sample_into(&(rt * p), &mut out);
                        *v = out[0];
                    }
                    -sdf_energy(buf, params) as f32
                },
            )
            .collect()
    }

    /// `κ_L`, the tempering of the fused term scored at the cell centres of `grid`. A cell's
    /// centre stands for the cell's mass: the SDF expert's bell around a pose has a standard
    /// deviation `s = √2·w` per axis (its selection puts its log at −¼ at the width `w`), and a
    /// cell of side `h` (`h = 2·(π²/N)^⅓` in rotation angle) spreads a point over a variance of
    /// `h²/12` per axis (a box's), so the bell seen at the centres is `s² + h²/12` wide:
    /// `κ_L = s²/(s² + h²/12)` (0.733 at level 3, 0.978 at level 5 for `w` = 2.5°: see the test).
    pub fn tempering(&self, grid: &crate::so3::GridLevel) -> f32 {
        let width = self.set.manifest.energy_selection.width.map_or(
            crate::experts::select::WidthCriterion::default().width_deg,
            |c| c.width_deg,
        );
        cell_tempering(width, grid.cell_volume())
    }

    /// Converts camera-frame points in the source mesh's units to normalised units; refuses point
    /// sets that cannot be this object at any pose (a wrong scale, or a box that holds more than
    /// the object), naming `field`.
    pub fn camera_points(
        &self,
        seen: &BackProjected,
        field: &str,
    ) -> Result<CameraPoints, EngineError> {
        let scale = self.set.manifest.object.normalisation.scale;
        let camera = CameraPoints {
            points: seen.points.iter().map(|p| (p / scale).cast()).collect(),
            centroid: (seen.centroid / scale).cast(),
        };
        let invalid = |message: String| EngineError::InvalidArgument {
            field: field.into(),
            message,
        };
        let c = camera.centroid;
        let spread = camera
            .points
            .iter()
            .map(|p| (p - c).norm())
            .fold(0f32, f32::max);
        if !c.iter().all(|v| v.is_finite()) || c.z <= 1.0 {
            return Err(invalid(format!(
                "the points' centroid is {:.3} object radii in front of the camera: the object \
                 would hold the camera (is the depth scale right?)",
                c.z
            )));
        }
        if spread > 3.0 {
            return Err(invalid(format!(
                "the points spread {spread:.2} object radii from their centroid, more than the \
                 object can: the depth scale is wrong, or the box holds more than the object \
                 (give a mask)"
            )));
        }
        Ok(camera)
    }

    /// The translation estimate `τ₀(R)` ([`ViewTable::initial_translation`]).
    pub fn initial_translation(&self, points: &CameraPoints, r: &Matrix3<f32>) -> Vector3<f32> {
        self.baked().1.initial_translation(points, r)
    }

    /// `−U(R, τ₀(R))` of the camera points for every candidate (row-major rotations), see
    /// [`DepthFusion::posed_energy`].
    pub fn posed_log_measure(&self, points: &CameraPoints, rotations: &[[f32; 9]]) -> Vec<f32> {
        rotations
            .par_iter()
            .map_init(Vec::new, |buf, m| {
                let r = Matrix3::from_row_slice(m);
                let t = self.initial_translation(points, &r);
                -self.posed_energy(points, &r, &t, buf)
            })
            .collect()
    }

    /// `U_SDF(R, τ)`: the SDF energy of the seen points at `x_i = Rᵀ(q_i − τ)`. (A free-space
    /// term, the object's material found in front of the points along their rays, was measured
    /// and dropped: on the L-bracket it changed LL by < 0.1 and AR@30 not at all, for 3× the
    /// lookups.)
    pub fn posed_energy(
        &self,
        points: &CameraPoints,
        r: &Matrix3<f32>,
        t: &Vector3<f32>,
        buf: &mut Vec<f32>,
    ) -> f32 {
        let sdf = self.sdf();
        let rt = r.transpose();
        buf.clear();
        buf.extend(points.points.iter().map(|p| sdf.value(&(rt * (p - t)))));
        sdf_energy(buf, self.params()) as f32
    }

    /// The translation that best fits the points for rotation `r` (row-major), from `τ₀(R)` by
    /// [`FIT_STEPS`] damped Gauss–Newton steps on `Σ f_SDF(Rᵀ(q_i − τ))²`, with `−U` there
    /// ([`DepthFusion::posed_energy`]).
    /// `∂f/∂τ = −R·∇f`, so a step is `δτ = R·(Σ g gᵀ + μI)⁻¹·Σ g f` (object-frame gradients `g`).
    pub fn fit_translation(&self, points: &CameraPoints, r: &[f32; 9]) -> (Vector3<f32>, f32) {
        let sdf = self.sdf();
        let r = Matrix3::from_row_slice(r);
        let rt = r.transpose();
        let mut t = self.initial_translation(points, &r);
        let mut values = Vec::new();
        let h = 0.5 * sdf.step();
        for _ in 0..FIT_STEPS {
            let mut normal = Matrix3::<f32>::zeros();
            let mut rhs = Vector3::<f32>::zeros();
            for p in &points.points {
                let x = rt * (p - t);
                let f = sdf.value(&x);
                let along = |e: Vector3<f32>| sdf.value(&(x + e * h)) - sdf.value(&(x - e * h));
                let g = Vector3::new(
                    along(Vector3::x()),
                    along(Vector3::y()),
                    along(Vector3::z()),
                ) / (2.0 * h);
                normal += g * g.transpose();
                rhs += g * f;
            }
            let damping = 1e-3 * points.points.len() as f32;
            let Some(inverse) = (normal + Matrix3::identity() * damping).try_inverse() else {
                break;
            };
            t += r * (inverse * rhs);
        }
        (t, -self.posed_energy(points, &r, &t, &mut values))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::so3::GridLevel;

    #[test]
    fn tempering_grows_to_one_as_cells_shrink_below_the_experts_width() {
        let kappa = |level| cell_tempering(2.5, GridLevel::new(level).unwrap().cell_volume());
        assert!((kappa(3) - 0.733).abs() < 5e-4, "{}", kappa(3));
        assert!((kappa(4) - 0.917).abs() < 5e-4, "{}", kappa(4));
        assert!((kappa(5) - 0.978).abs() < 5e-4, "{}", kappa(5));
        assert!(kappa(2) < kappa(3));
    }
}
