//! The nested equivolumetric SO(3) grid (Yershova et al. 2010 as used by IPDF, re-indexed nested
//! as in SpyroPose), docs/DESIGN.md §1, with compact cells at the poles.
//!
//! Level `L` has `N_L = 72·8^L` cells: the `12·4^L` nested HEALPix pixels of depth `L` times
//! `6·2^L` tilt bins. Write `R = Rz(φ)·Ry(θ)·Rz(ψ)` (ZYZ), so that `R·e_z = (θ, φ)`. Cell `(p, t)`
//! holds the rotations whose z axis falls in pixel `p` and whose **tilt** `τ` falls in
//! `[t, t + 1)·2π/(6·2^L)`, where the tilt depends on the HEALPix base pixel of `p` (its depth-0
//! ancestor, so that one rule holds for a pixel and all its descendants):
//!
//! - equatorial base pixels 4–7 (`|z| ≤ 2/3`): `τ = ψ`, as in IPDF;
//! - north polar base pixels 0–3: `τ = ψ + φ`, the in-plane angle `R → Rz(φ + ψ)` as `θ → 0`;
//! - south polar base pixels 8–11: `τ = ψ − φ`, since `R → Ry(π)·Rz(ψ − φ)` as `θ → π`.
//!
//! Its centre uses the pixel centre `(θ_p, φ_p)` and the middle of the tilt bin. Index =
//! `p·n_tilts + t`.
//!
//! The map `(φ, θ, ψ) ↦ (φ, θ, τ)` is a shear with unit Jacobian, and the Haar measure in ZYZ
//! angles is `sin θ dθ dφ dψ`; HEALPix pixels have equal areas, so all cells have the same volume
//! `π²/N_L`, and nesting is exact: the children of `(p, t)` are pixels `4p … 4p+3` times tilts
//! `2t, 2t+1`. With plain `ψ` everywhere (IPDF's grid, the convention before 2026-11) the cells of
//! the pixels that touch a pole are slivers ~90° long at every level, because near a pole `φ` and
//! `ψ` mix; with the per-hemisphere tilt every cell's diameter halves with each level
//! ([`covering_radius`]). [`GridLevel::legacy_rotation`] keeps the old centres for files that
//! recorded cells in the old convention.

use std::f64::consts::{PI, TAU};

use nalgebra::{Matrix3, Rotation3, Vector3};
use rayon::prelude::*;

use super::So3Error;

/// Highest level supported (level 6 has 18 874 368 cells).
pub const MAX_LEVEL: u8 = 6;

/// How a file's cell indices are to be read: the grid's convention when it wrote them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GridConvention {
    /// Plain `ψ` tilt everywhere (IPDF's grid; this project before 2026-11). Files without a
    /// convention were written in it.
    #[default]
    IpdfZyz,
    /// The per-hemisphere tilt with compact polar cells (module docs; the current grid).
    CompactPoles,
}

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

    /// Centre rotation of cell `index`: `Rz(φ_p)·Ry(θ_p)·Rz(τ_t − s·φ_p)`, where `τ_t` is the
    /// middle of tilt bin `t` and `s` the sign of the pixel's tilt rule (module docs).
    ///
    /// # Panics
    /// If `index >= len()`; use [`GridLevel::check_index`] on untrusted input.
    pub fn rotation(&self, index: u64) -> Rotation3<f64> {
        let (p, t) = (index / self.n_tilts, index % self.n_tilts);
        let frame = self.pixel_frames[p as usize];
        let psi = self.tilt_centre(t) - self.tilt_sign(p) * self.pixel_azimuth(p);
        Rotation3::from_matrix_unchecked(frame * rot_z_matrix(psi))
    }

    /// Centre of cell `index` in the grid convention before compact polar cells (plain `ψ` tilt
    /// everywhere): only for reading files that recorded cells in that convention.
    pub fn legacy_rotation(&self, index: u64) -> Rotation3<f64> {
        let (p, t) = (index / self.n_tilts, index % self.n_tilts);
        let frame = self.pixel_frames[p as usize];
        Rotation3::from_matrix_unchecked(frame * rot_z_matrix(self.tilt_centre(t)))
    }

    /// Centre of cell `index` as the grid of `convention` defines it.
    pub fn rotation_in(&self, convention: GridConvention, index: u64) -> Rotation3<f64> {
        match convention {
            GridConvention::IpdfZyz => self.legacy_rotation(index),
            GridConvention::CompactPoles => self.rotation(index),
        }
    }

    /// `+1` for pixels in a north polar base pixel (`τ = ψ + φ`), `−1` in a south one
    /// (`τ = ψ − φ`), `0` in an equatorial one (`τ = ψ`).
    pub(crate) fn tilt_sign(&self, pixel: u64) -> f64 {
        tilt_sign_of_base(pixel >> (2 * self.level as u32))
    }

    /// Azimuth `φ_p` of a pixel's centre (the z axis of its frame).
    fn pixel_azimuth(&self, pixel: u64) -> f64 {
        let f = &self.pixel_frames[pixel as usize];
        f[(1, 2)].atan2(f[(0, 2)])
    }

    /// Tilt angle `τ` at the centre of bin `t`.
    fn tilt_centre(&self, t: u64) -> f64 {
        (t as f64 + 0.5) * TAU / self.n_tilts as f64
    }

    /// All cell centres as row-major `f32` matrices, in index order (parallel).
    pub fn matrices_f32(&self) -> Vec<[f32; 9]> {
        let mut out = vec![[0f32; 9]; self.len()];
        let n_tilts = self.n_tilts;
        out.par_chunks_mut(n_tilts as usize)
            .enumerate()
            .for_each(|(p, chunk)| {
                for (t, slot) in chunk.iter_mut().enumerate() {
                    let m = self.rotation(p as u64 * n_tilts + t as u64);
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
    /// then the bin of its tilt `τ` (module docs). O(1).
    pub fn cell_of(&self, r: &Rotation3<f64>) -> u64 {
        let (p, t) = pixel_and_tilt_fraction(r, self.level);
        // `t` is ψ/2π in [0, 1); multiplying by a power of two is exact, so the tilt bins nest
        // exactly across levels.
        let bin = ((t * self.n_tilts as f64) as u64).min(self.n_tilts - 1);
        p * self.n_tilts + bin
    }
}

/// HEALPix pixel at `depth` of the z axis of `r`, and the tilt `τ/2π ∈ [0, 1)`.
///
/// Each tilt is read from the matrix in the form that stays well conditioned where it is used:
/// `ψ + φ = atan2(r₁₀ − r₀₁, r₀₀ + r₁₁)` (the factor `1 + cos θ` never vanishes in the north cap),
/// `ψ − φ = atan2(r₁₀ + r₀₁, r₁₁ − r₀₀)` (factor `1 − cos θ`, south cap), `ψ = atan2(r₂₁, −r₂₀)`
/// (factor `sin θ`, equatorial belt).
fn pixel_and_tilt_fraction(r: &Rotation3<f64>, depth: u8) -> (u64, f64) {
    let m = r.matrix();
    let z = Vector3::new(m[(0, 2)], m[(1, 2)], m[(2, 2)]);
    let lat = z.z.clamp(-1.0, 1.0).asin();
    let lon = z.y.atan2(z.x).rem_euclid(TAU);
    let pixel = cdshealpix::nested::hash(depth, lon, lat);
    let sign = tilt_sign_of_base(pixel >> (2 * depth as u32));
    let tau = if sign > 0.0 {
        (m[(1, 0)] - m[(0, 1)]).atan2(m[(0, 0)] + m[(1, 1)])
    } else if sign < 0.0 {
        (m[(1, 0)] + m[(0, 1)]).atan2(m[(1, 1)] - m[(0, 0)])
    } else {
        m[(2, 1)].atan2(-m[(2, 0)])
    };
    (pixel, (tau.rem_euclid(TAU) / TAU).min(1.0 - f64::EPSILON))
}

/// The sign `s` of the tilt rule `τ = ψ + s·φ` of a HEALPix base pixel (depth 0, nested): the
/// north polar cap is 0–3, the equatorial belt 4–7, the south polar cap 8–11.
fn tilt_sign_of_base(base: u64) -> f64 {
    match base {
        0..=3 => 1.0,
        8..=11 => -1.0,
        _ => 0.0,
    }
}

/// An upper bound of the angle from any rotation to the centre of its cell at `level`:
/// `r_L = min(60°, 90° / 2^L)`. The worst angles found (test
/// `every_rotation_lies_within_the_covering_radius`, 90 000 rotations of which 40 000 lie within
/// 1° of a pole) are 56.3°, 35.4°, 18.6°, 9.67°, 4.93°, 2.35° and 1.24° at levels 0–6, i.e. at
/// most 79.5°/2^L; the bound keeps ~13 % over that.
pub fn covering_radius(level: u8) -> f64 {
    (90f64 / f64::from(1u32 << level)).min(60.0).to_radians()
}

/// Writes the cell centres of `grid` as CSV (`index,qw,qx,qy,qz`, index order, `w ≥ 0`, 9
/// decimals), calling `progress` with the index every 65 536 cells.
pub fn write_centres_csv(
    grid: &GridLevel,
    w: &mut impl std::io::Write,
    mut progress: impl FnMut(u64),
) -> std::io::Result<()> {
    writeln!(w, "index,qw,qx,qy,qz")?;
    for i in 0..grid.len() as u64 {
        let q = super::to_quaternion(&grid.rotation(i));
        writeln!(w, "{i},{:.9},{:.9},{:.9},{:.9}", q[0], q[1], q[2], q[3])?;
        if i % 65_536 == 0 {
            progress(i);
        }
    }
    w.flush()
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
