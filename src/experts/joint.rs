//! Both baked experts in one grid of 16-lane records (`f_SDF`, the 12 keys of `f_SE`, zeros),
//! one 64-byte cache line per grid point: the trainer's targets are bound by these lookups
//! (paper Eq. 3–4 at B·K candidates × 100 points a step), and a record that is one AVX-512
//! register interpolates in 7 vector steps instead of 8 × 13 scalar ones.
//!
//! [`JointGrid::squared_energies`] is the training default's two sums (L2 SDF, squared key
//! distance) fused with the lookups: on 512-bit intrinsics where the core has AVX-512F, else one
//! portable body compiled for AVX2 + FMA or for the baseline, the widest that `ALIGNIST_KERNELS`
//! allows (`avx2`, `portable`); the three agree to float rounding (test).

use nalgebra::{Matrix3, Vector3};

use super::baked::VoxelGrid;

/// Lanes of a record: `f_SDF`, up to 15 key channels, zeros.
pub const LANES: usize = 16;

/// One grid point's values, aligned to a cache line.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[repr(C, align(64))]
pub struct Record(pub [f32; LANES]);

/// `f_SDF` and `f_SE` at every point of one `res³` grid over `[−bound, bound]³`.
#[derive(Debug, Clone, PartialEq)]
pub struct JointGrid {
    res: usize,
    bound: f32,
    keys: usize,
    data: Vec<Record>,
}

/// The cell of `p` (clamped to the grid): the offset of its lowest corner and the fractions
/// along x, y, z (as [`VoxelGrid`] interpolates).
#[inline(always)]
fn cell(res: usize, bound: f32, p: &Vector3<f32>) -> (usize, [f32; 3]) {
    let scale = (res - 1) as f32 / (2.0 * bound);
    let max = (res - 1) as f32;
    let axis = |c: f32| {
        let g = ((c + bound) * scale).clamp(0.0, max);
        let i = (g as usize).min(res - 2);
        (i, g - i as f32)
    };
    let ((ix, tx), (iy, ty), (iz, tz)) = (axis(p.x), axis(p.y), axis(p.z));
    ((iz * res + iy) * res + ix, [tx, ty, tz])
}

impl JointGrid {
    /// Joins an SDF grid (1 channel) and a key grid (1 to 15 channels) of the same resolution
    /// and bound; `None` otherwise.
    pub fn new(sdf: &VoxelGrid, keys: &VoxelGrid) -> Option<JointGrid> {
        let (res, bound) = (sdf.resolution(), sdf.bound());
        if sdf.channels() != 1
            || !(1..LANES).contains(&keys.channels())
            || keys.resolution() != res
            || keys.bound() != bound
        {
            return None;
        }
        let k = keys.channels();
        let data = sdf
            .values()
            .iter()
            .zip(keys.values().chunks_exact(k))
            .map(|(&s, key)| {
                let mut r = [0f32; LANES];
                r[0] = s;
                r[1..=k].copy_from_slice(key);
                Record(r)
            })
            .collect();
        Some(JointGrid {
            res,
            bound,
            keys: k,
            data,
        })
    }

    /// Number of key channels.
    pub fn key_channels(&self) -> usize {
        self.keys
    }

    /// The record at `p`, interpolated trilinearly (lerps along x, then y, then z).
    pub fn sample(&self, p: &Vector3<f32>) -> [f32; LANES] {
        let (base, t) = cell(self.res, self.bound, p);
        lerp_cell(&self.data, base, self.res, t).0
    }

    /// A record holding `keys` in the key lanes and 0 elsewhere: what a point's lookup is
    /// compared with in [`JointGrid::squared_energies`].
    pub fn seen(&self, keys: &[f32]) -> Record {
        let mut r = [0f32; LANES];
        r[1..=self.keys].copy_from_slice(&keys[..self.keys]);
        Record(r)
    }

    /// `(Σ_i f_SDF(x'_i)², Σ_i ‖f_SE(x'_i) − f_SE(x⁰_i)‖²)` over `x'_i = map · x⁰_i`, with
    /// `seen[i]` from [`JointGrid::seen`] of `f_SE(x⁰_i)`: the sums of the L2 SDF energy and the
    /// squared key energy (paper Eq. 3–4 in their graded form) for one candidate.
    pub fn squared_energies(
        &self,
        map: &Matrix3<f32>,
        x0: &[Vector3<f32>],
        seen: &[Record],
    ) -> (f32, f32) {
        assert_eq!(x0.len(), seen.len(), "one seen record per point");
        #[cfg(target_arch = "x86_64")]
        {
            match vector_path() {
                // SAFETY: `vector_path` found AVX-512F on this core.
                Vectors::Avx512 => return unsafe { self.squared_energies_avx512(map, x0, seen) },
                // SAFETY: `vector_path` found AVX2 and FMA on this core.
                Vectors::Avx2 => return unsafe { self.squared_energies_avx2(map, x0, seen) },
                Vectors::Portable => {}
            }
        }
        self.squared_energies_portable(map, x0, seen)
    }

    /// [`JointGrid::squared_energies`] compiled for the baseline.
    pub fn squared_energies_portable(
        &self,
        map: &Matrix3<f32>,
        x0: &[Vector3<f32>],
        seen: &[Record],
    ) -> (f32, f32) {
        self.squared_body(map, x0, seen)
    }

    /// [`JointGrid::squared_energies`] compiled for AVX2 + FMA (a record is two registers).
    ///
    /// # Safety
    /// The core has AVX2 and FMA.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn squared_energies_avx2(
        &self,
        map: &Matrix3<f32>,
        x0: &[Vector3<f32>],
        seen: &[Record],
    ) -> (f32, f32) {
        self.squared_body(map, x0, seen)
    }

    /// [`JointGrid::squared_energies`] on 512-bit vectors: a record is one register (the
    /// compiler's own vectorisation of the portable body was 1.5–1.9× slower here).
    ///
    /// # Safety
    /// The core has AVX-512F.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn squared_energies_avx512(
        &self,
        map: &Matrix3<f32>,
        x0: &[Vector3<f32>],
        seen: &[Record],
    ) -> (f32, f32) {
        use std::arch::x86_64::*;
        let (res, slab) = (self.res, self.res * self.res);
        let data = self.data.as_ptr() as *const f32;
        let mut acc = _mm512_setzero_ps();
        self.for_each_cell(map, x0, seen, |base, [tx, ty, tz], s| {
            // SAFETY: `cell` keeps every corner's offset (base + {0,1} + {0,res} + {0,slab})
            // inside the res³ records; each record is 64-byte aligned; the core has AVX-512F.
            unsafe {
                let at = |o: usize| _mm512_load_ps(data.add(o * LANES));
                let lerp = |a: __m512, b: __m512, t: f32| {
                    _mm512_fmadd_ps(_mm512_sub_ps(b, a), _mm512_set1_ps(t), a)
                };
                let along_x = |o: usize| lerp(at(o), at(o + 1), tx);
                let c0 = lerp(along_x(base), along_x(base + res), ty);
                let c1 = lerp(along_x(base + slab), along_x(base + slab + res), ty);
                let v = lerp(c0, c1, tz);
                let d = _mm512_sub_ps(v, _mm512_load_ps(s.0.as_ptr()));
                acc = _mm512_fmadd_ps(d, d, acc);
            }
        });
        let mut lanes = [0f32; LANES];
        // SAFETY: `lanes` holds 16 floats.
        unsafe { _mm512_storeu_ps(lanes.as_mut_ptr(), acc) };
        (lanes[0], lanes[1..].iter().sum())
    }

    /// The portable body of [`JointGrid::squared_energies`], inlined into the wrappers above so
    /// that the compiler vectorises the 16-lane records for their target.
    #[inline(always)]
    fn squared_body(&self, map: &Matrix3<f32>, x0: &[Vector3<f32>], seen: &[Record]) -> (f32, f32) {
        let mut acc = [0f32; LANES];
        self.for_each_cell(map, x0, seen, |base, t, s| {
            let v = lerp_cell(&self.data, base, self.res, t);
            for ((acc, v), s) in acc.iter_mut().zip(v.0).zip(s.0) {
                *acc += (v - s) * (v - s);
            }
        });
        (acc[0], acc[1..].iter().sum())
    }

    /// `point(base, t, seen_i)` for the cell of every `x'_i = map · x⁰_i`, in groups of 8
    /// points: every cell of a group is found and its corners' cache lines asked for before
    /// the group is visited, so the lookups' cache misses overlap.
    #[inline(always)]
    fn for_each_cell(
        &self,
        map: &Matrix3<f32>,
        x0: &[Vector3<f32>],
        seen: &[Record],
        mut point: impl FnMut(usize, [f32; 3], &Record),
    ) {
        const GROUP: usize = 8;
        for (xs, ss) in x0.chunks(GROUP).zip(seen.chunks(GROUP)) {
            let mut cells = [(0usize, [0f32; 3]); GROUP];
            for (c, x) in cells.iter_mut().zip(xs) {
                *c = cell(self.res, self.bound, &(map * x));
                prefetch_cell(&self.data, c.0, self.res);
            }
            for (&(base, t), s) in cells.iter().zip(ss) {
                point(base, t, s);
            }
        }
    }
}

/// Asks for the cache lines of the 8 corners of the cell whose lowest corner is record `base`.
#[inline(always)]
fn prefetch_cell(data: &[Record], base: usize, res: usize) {
    #[cfg(target_arch = "x86_64")]
    for o in [base, base + res, base + res * res, base + res * res + res] {
        for r in &data[o..o + 2] {
            // SAFETY: SSE is part of x86_64; `r` is a valid address (a prefetch never faults).
            unsafe {
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                    r as *const Record as *const i8,
                )
            };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (data, base, res);
}

/// The widest vectors the lookups may use.
#[cfg(target_arch = "x86_64")]
#[derive(Debug, Clone, Copy)]
enum Vectors {
    Avx512,
    Avx2,
    Portable,
}

/// The widest vectors of this core that `ALIGNIST_KERNELS` allows (decided once).
#[cfg(target_arch = "x86_64")]
fn vector_path() -> Vectors {
    static PATH: std::sync::OnceLock<Vectors> = std::sync::OnceLock::new();
    *PATH.get_or_init(|| {
        let kernels = crate::net::Kernels::from_env();
        if kernels.allows_avx512() && std::is_x86_feature_detected!("avx512f") {
            Vectors::Avx512
        } else if kernels.allows_own()
            && std::is_x86_feature_detected!("avx2")
            && std::is_x86_feature_detected!("fma")
        {
            Vectors::Avx2
        } else {
            Vectors::Portable
        }
    })
}

/// `a + (b − a)·t`, lane by lane (no `mul_add`: without FMA in the target it is a library call).
#[inline(always)]
fn lerp(a: &Record, b: &Record, t: f32) -> Record {
    Record(std::array::from_fn(|l| a.0[l] + (b.0[l] - a.0[l]) * t))
}

/// Trilinear interpolation of the cell whose lowest corner is record `base`.
#[inline(always)]
fn lerp_cell(data: &[Record], base: usize, res: usize, [tx, ty, tz]: [f32; 3]) -> Record {
    let slab = res * res;
    let corners = &data[base..=base + slab + res + 1];
    let x00 = lerp(&corners[0], &corners[1], tx);
    let x10 = lerp(&corners[res], &corners[res + 1], tx);
    let x01 = lerp(&corners[slab], &corners[slab + 1], tx);
    let x11 = lerp(&corners[slab + res], &corners[slab + res + 1], tx);
    lerp(&lerp(&x00, &x10, ty), &lerp(&x01, &x11, ty), tz)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    fn grids() -> (VoxelGrid, VoxelGrid) {
        let sdf = VoxelGrid::bake(11, 1.05, 1, |p| {
            p.iter().map(|v| v.norm() - 0.6 + 0.1 * v.x * v.y).collect()
        });
        let keys = VoxelGrid::bake(11, 1.05, 12, |p| {
            p.iter()
                .flat_map(|v| (0..12).map(move |k| (k as f32 * 0.7 + v.x).sin() * v.y - v.z * v.z))
                .collect()
        });
        (sdf, keys)
    }

    #[test]
    fn a_record_holds_the_sdf_then_the_keys_then_zeros() {
        let (sdf, keys) = grids();
        let joint = JointGrid::new(&sdf, &keys).unwrap();
        assert_eq!(joint.key_channels(), 12);
        for p in [
            Vector3::new(0.13f32, -0.71, 0.4),
            Vector3::new(1.04, 1.04, -1.04),
            Vector3::new(-3.0, 0.0, 2.5),
        ] {
            let r = joint.sample(&p);
            assert!((r[0] - sdf.value(&p)).abs() < 1e-5, "{p:?}");
            let k = keys.sample(&[p]);
            assert!(r[1..13].iter().zip(&k).all(|(a, b)| (a - b).abs() < 1e-5));
            assert!(r[13..].iter().all(|&z| z == 0.0));
        }
        // Other resolutions, or more keys than lanes, do not join.
        let coarse = VoxelGrid::bake(7, 1.05, 1, |p| p.iter().map(|v| v.x).collect());
        assert!(JointGrid::new(&coarse, &keys).is_none());
        let wide = VoxelGrid::bake(11, 1.05, 16, |p| vec![0.0; p.len() * 16]);
        assert!(JointGrid::new(&sdf, &wide).is_none());
        let none = VoxelGrid::bake(11, 1.05, 0, |_| Vec::new());
        assert!(JointGrid::new(&sdf, &none).is_none());
    }

    #[test]
    fn the_fused_sums_agree_with_sampling_point_by_point_on_every_path() {
        let (sdf, keys) = grids();
        let joint = JointGrid::new(&sdf, &keys).unwrap();
        let x0: Vec<Vector3<f32>> = (0..37)
            .map(|i| {
                let a = i as f32 * 0.37;
                Vector3::new(a.cos() * 0.6, a.sin() * 0.5, (a * 0.3).sin() * 0.7)
            })
            .collect();
        let seen: Vec<Record> = x0.iter().map(|x| joint.seen(&keys.sample(&[*x]))).collect();
        let map: Matrix3<f32> = *Rotation3::from_euler_angles(0.4, -1.1, 2.3).matrix();
        let (mut want_sdf, mut want_keys) = (0f64, 0f64);
        for (x, s) in x0.iter().zip(&seen) {
            let moved = map * x;
            want_sdf += (sdf.value(&moved) as f64).powi(2);
            let k = keys.sample(&[moved]);
            want_keys += k
                .iter()
                .zip(&s.0[1..])
                .map(|(a, b)| ((a - b) as f64).powi(2))
                .sum::<f64>();
        }
        assert!(want_sdf > 0.1 && want_keys > 0.1, "a test that can fail");
        let close = |(s, k): (f32, f32)| {
            ((s as f64 - want_sdf).abs() / want_sdf) < 1e-4
                && ((k as f64 - want_keys).abs() / want_keys) < 1e-4
        };
        assert!(close(joint.squared_energies(&map, &x0, &seen)));
        assert!(close(joint.squared_energies_portable(&map, &x0, &seen)));
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                // SAFETY: checked just above.
                assert!(close(unsafe {
                    joint.squared_energies_avx2(&map, &x0, &seen)
                }));
            }
            if std::is_x86_feature_detected!("avx512f") {
                // SAFETY: checked just above.
                assert!(close(unsafe {
                    joint.squared_energies_avx512(&map, &x0, &seen)
                }));
            }
        }
        // At the identity every point keeps its key: the key sum is (nearly) zero.
        let (_, k) = joint.squared_energies(&Matrix3::identity(), &x0, &seen);
        assert!(k < 1e-8, "{k}");
    }
}
