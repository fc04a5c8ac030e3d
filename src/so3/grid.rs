//! The nested equivolumetric SO(3) grid (Yershova et al. 2010 as used by IPDF, re-indexed nested
//! as in SpyroPose), DESIGN.md §1.
//!
//! Level `L` has `N_L = 72·8^L` cells: the `12·4^L` nested HEALPix pixels of depth `L` times
//! `6·2^L` tilt bins. Cell `(p, t)` holds the rotations `R = Rz(φ)·Ry(θ)·Rz(ψ)` whose z axis
//! `R·e_z = (θ, φ)` falls in pixel `p` and whose tilt `ψ` falls in `[t, t + 1)·2π/(6·2^L)`; its
//! centre uses the pixel centre and `ψ = (t + ½)·2π/(6·2^L)`. Index = `p·n_tilts + t`.
//!
//! Because HEALPix pixels have equal areas and the Haar measure in ZYZ angles is
//! `sin θ dθ dφ dψ`, all cells have the same volume `π²/N_L`, and nesting is exact: the children of
//! `(p, t)` are pixels `4p … 4p+3` times tilts `2t, 2t+1`.

use std::f64::consts::{PI, TAU};

use nalgebra::{Matrix3, Rotation3, Vector3};
use rayon::prelude::*;

use super::So3Error;

/// Highest level supported (level 6 has 18 874 368 cells).
pub const MAX_LEVEL: u8 = 6;

/// Number of tilt bins at level 0; level `L` has `BASE_TILTS · 2^L`.
const BASE_TILTS: u64 = 6;

/// One level of the nested grid. Cheap to build: it stores one `Rz(φ)·Ry(θ)` matrix per HEALPix
/// pixel; cell rotations are formed on demand (or in bulk with [`GridLevel::matrices_f32`]).
#[derive(Debug, Clone)]
pub struct GridLevel {
    level: u8,
    n_tilts: u64,
    /// `Rz(φ_p)·Ry(θ_p)` for every pixel centre, in nested order.
    pixel_frames: Vec<Matrix3<f64>>,
}

impl GridLevel {
    /// The grid at `level` (0 ..= [`MAX_LEVEL`]).
    pub fn new(level: u8) -> Result<Self, So3Error> {
        if level > MAX_LEVEL {
            return Err(So3Error::LevelTooHigh {
                level,
                max: MAX_LEVEL,
            });
        }
        let n_pix = cdshealpix::nested::n_hash(level);
        let pixel_frames = (0..n_pix)
            .into_par_iter()
            .map(|p| {
                let (lon, lat) = cdshealpix::nested::center(level, p);
                pixel_frame(PI / 2.0 - lat, lon)
            })
            .collect();
        Ok(Self {
            level,
            n_tilts: BASE_TILTS << level,
            pixel_frames,
        })
    }

    /// The level `L` of this grid.
    pub fn level(&self) -> u8 {
        self.level
    }

    /// Number of cells, `72·8^L`.
    pub fn len(&self) -> usize {
        self.pixel_frames.len() * self.n_tilts as usize
    }

    /// Always false: every level has at least 72 cells.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Number of tilt bins, `6·2^L`.
    pub fn n_tilts(&self) -> u64 {
        self.n_tilts
    }

    /// Number of HEALPix pixels, `12·4^L`.
    pub fn n_pixels(&self) -> u64 {
        self.pixel_frames.len() as u64
    }

    /// Volume of every cell, `π²/N_L` (IPDF's convention: SO(3) has volume π²).
    pub fn cell_volume(&self) -> f64 {
        PI * PI / self.len() as f64
    }

    /// Checks that `index` names a cell of this level.
    pub fn check_index(&self, index: u64) -> Result<(), So3Error> {
        if index as usize >= self.len() {
            return Err(So3Error::IndexOutOfRange {
                index,
                level: self.level,
                len: self.len() as u64,
            });
        }
        Ok(())
    }

    /// Centre rotation of cell `index`: `Rz(φ_p)·Ry(θ_p)·Rz(ψ_t)`.
    ///
    /// # Panics
    /// If `index >= len()`; use [`GridLevel::check_index`] on untrusted input.
    pub fn rotation(&self, index: u64) -> Rotation3<f64> {
        let (p, t) = (index / self.n_tilts, index % self.n_tilts);
        let frame = self.pixel_frames[p as usize];
        Rotation3::from_matrix_unchecked(frame * rot_z_matrix(self.tilt_centre(t)))
    }

    /// Whether cell `index` lies in a HEALPix pixel that touches a pole.
    ///
    /// Near the poles the ZYZ tilt `ψ` and azimuth `φ` mix (`Rz(φ)·Ry(θ)·Rz(ψ) → Rz(φ + ψ)` as
    /// `θ → 0`), and the pixels that touch a pole span 90° of azimuth at every depth. Their cells
    /// therefore stay slivers about 90° long however fine the level, although their volume is
    /// exactly `π²/N` like every other cell. They hold a fraction `2/(3·4^L)` of SO(3) (8 of
    /// `12·4^L` pixels). Everywhere else the cell diameter halves with each level.
    pub fn is_polar_cell(&self, index: u64) -> bool {
        let p = index / self.n_tilts;
        cdshealpix::nested::vertices(self.level, p)
            .iter()
            .any(|&(_, lat)| (lat.abs() - PI / 2.0).abs() < 1e-9)
    }

    /// Tilt angle `ψ` at the centre of bin `t`.
    fn tilt_centre(&self, t: u64) -> f64 {
        (t as f64 + 0.5) * TAU / self.n_tilts as f64
    }

    /// All cell centres as row-major `f32` matrices, in index order (parallel).
    pub fn matrices_f32(&self) -> Vec<[f32; 9]> {
        let tilts: Vec<Matrix3<f64>> = (0..self.n_tilts)
            .map(|t| rot_z_matrix(self.tilt_centre(t)))
            .collect();
        let mut out = vec![[0f32; 9]; self.len()];
        out.par_chunks_mut(self.n_tilts as usize)
            .zip(self.pixel_frames.par_iter())
            .for_each(|(chunk, frame)| {
                for (slot, tilt) in chunk.iter_mut().zip(&tilts) {
                    let m = frame * tilt;
                    for r in 0..3 {
                        for c in 0..3 {
                            slot[r * 3 + c] = m[(r, c)] as f32;
                        }
                    }
                }
            });
        out
    }

    /// All cell centres as quaternions `(w, x, y, z)`, `w ≥ 0`, in index order (parallel).
    pub fn quaternions(&self) -> Vec<[f64; 4]> {
        (0..self.len() as u64)
            .into_par_iter()
            .map(|i| super::to_quaternion(&self.rotation(i)))
            .collect()
    }

    /// The 8 children of cell `index` at level `L + 1`, in index order.
    pub fn children(&self, index: u64) -> [u64; 8] {
        let (p, t) = (index / self.n_tilts, index % self.n_tilts);
        let child_tilts = self.n_tilts * 2;
        let mut out = [0u64; 8];
        for (k, slot) in out.iter_mut().enumerate() {
            let k = k as u64;
            *slot = (4 * p + k / 2) * child_tilts + 2 * t + k % 2;
        }
        out
    }

    /// The parent at level `L − 1` of cell `index` of this level (`None` at level 0).
    pub fn parent(&self, index: u64) -> Option<u64> {
        if self.level == 0 {
            return None;
        }
        let (p, t) = (index / self.n_tilts, index % self.n_tilts);
        Some((p / 4) * (self.n_tilts / 2) + t / 2)
    }

    /// The cell that contains `r` by construction: the HEALPix hash at depth `L` of its z axis,
    /// then the bin of its tilt `ψ = atan2(r₂₁, −r₂₀)` (ZYZ angles). O(1).
    pub fn cell_of(&self, r: &Rotation3<f64>) -> u64 {
        let (p, t) = pixel_and_tilt_fraction(r, self.level);
        // `t` is ψ/2π in [0, 1); multiplying by a power of two is exact, so the tilt bins nest
        // exactly across levels.
        let bin = ((t * self.n_tilts as f64) as u64).min(self.n_tilts - 1);
        p * self.n_tilts + bin
    }
}

/// HEALPix pixel at `depth` of the z axis of `r`, and the tilt `ψ/2π ∈ [0, 1)`.
fn pixel_and_tilt_fraction(r: &Rotation3<f64>, depth: u8) -> (u64, f64) {
    let m = r.matrix();
    let z = Vector3::new(m[(0, 2)], m[(1, 2)], m[(2, 2)]);
    let lat = z.z.clamp(-1.0, 1.0).asin();
    let lon = z.y.atan2(z.x).rem_euclid(TAU);
    let pixel = cdshealpix::nested::hash(depth, lon, lat);
    let psi = m[(2, 1)].atan2(-m[(2, 0)]).rem_euclid(TAU);
    (pixel, (psi / TAU).min(1.0 - f64::EPSILON))
}

/// `Rz(φ)·Ry(θ)`: the frame whose z axis has polar angle θ and azimuth φ.
pub(crate) fn pixel_frame(theta: f64, phi: f64) -> Matrix3<f64> {
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    let rz = Matrix3::new(cp, -sp, 0.0, sp, cp, 0.0, 0.0, 0.0, 1.0);
    let ry = Matrix3::new(ct, 0.0, st, 0.0, 1.0, 0.0, -st, 0.0, ct);
    rz * ry
}

pub(crate) fn rot_z_matrix(angle: f64) -> Matrix3<f64> {
    let (s, c) = angle.sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_follow_72_times_8_to_the_level() {
        for level in 0..=4u8 {
            let g = GridLevel::new(level).unwrap();
            assert_eq!(g.len(), 72 * 8usize.pow(level as u32));
            assert_eq!(g.n_pixels() * g.n_tilts(), g.len() as u64);
        }
        assert!(matches!(
            GridLevel::new(7),
            Err(So3Error::LevelTooHigh { level: 7, .. })
        ));
    }

    #[test]
    fn children_and_parent_are_inverse() {
        let g1 = GridLevel::new(1).unwrap();
        let g2 = GridLevel::new(2).unwrap();
        let mut seen = vec![false; g2.len()];
        for i in 0..g1.len() as u64 {
            for c in g1.children(i) {
                assert_eq!(g2.parent(c), Some(i));
                assert!(!seen[c as usize], "child {c} listed twice");
                seen[c as usize] = true;
            }
        }
        assert!(seen.iter().all(|&s| s), "children cover the next level");
        assert_eq!(GridLevel::new(0).unwrap().parent(5), None);
    }

    #[test]
    fn bulk_matrices_match_single_rotations() {
        let g = GridLevel::new(1).unwrap();
        let bulk = g.matrices_f32();
        for i in [0u64, 1, 77, 300, 575] {
            let m = super::super::to_row_major_f32(&g.rotation(i));
            for k in 0..9 {
                assert!((m[k] - bulk[i as usize][k]).abs() < 1e-6);
            }
        }
    }
}
