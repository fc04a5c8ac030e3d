//! Dense voxel bakes of the experts: a trained network evaluated once on a regular grid over
//! `[−bound, bound]³`, then read back with trilinear interpolation. Scoring thousands of
//! rotations × 100 points per training image then costs lookups, not network passes.

use nalgebra::Vector3;

/// A `res³ × channels` grid of values over `[−bound, bound]³` (x fastest, then y, then z).
#[derive(Debug, Clone, PartialEq)]
pub struct VoxelGrid {
    res: usize,
    bound: f32,
    channels: usize,
    data: Vec<f32>,
}

impl VoxelGrid {
    /// Evaluates `f` (points → row-major `n × channels`) at the `res³` grid points.
    pub fn bake(
        res: usize,
        bound: f32,
        channels: usize,
        f: impl Fn(&[Vector3<f32>]) -> Vec<f32>,
    ) -> VoxelGrid {
        let res = res.max(2);
        let step = 2.0 * bound / (res - 1) as f32;
        let coord = |i: usize| -bound + i as f32 * step;
        let mut points = Vec::with_capacity(res * res * res);
        for z in 0..res {
            for y in 0..res {
                for x in 0..res {
                    points.push(Vector3::new(coord(x), coord(y), coord(z)));
                }
            }
        }
        let data = f(&points);
        assert_eq!(
            data.len(),
            points.len() * channels,
            "baked function output size"
        );
        VoxelGrid {
            res,
            bound,
            channels,
            data,
        }
    }

    /// Half the side of the grid's cube.
    pub fn bound(&self) -> f32 {
        self.bound
    }

    /// The values, `res³ × channels` (x fastest, then y, then z).
    pub fn values(&self) -> &[f32] {
        &self.data
    }

    /// Number of values per grid point.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Spacing of the grid points.
    pub fn step(&self) -> f32 {
        2.0 * self.bound / (self.res - 1) as f32
    }

    /// The first channel at `p` (trilinear, clamped to the grid): [`VoxelGrid::sample_into`]'s
    /// value, with the interpolation written out (depth fusion calls this millions of times).
    #[inline]
    pub fn value(&self, p: &Vector3<f32>) -> f32 {
        let scale = (self.res - 1) as f32 / (2.0 * self.bound);
        let max = (self.res - 1) as f32;
        let cell = |c: f32| {
            let g = ((c + self.bound) * scale).clamp(0.0, max);
            let i = (g as usize).min(self.res - 2);
            (i, g - i as f32)
        };
        let ((ix, tx), (iy, ty), (iz, tz)) = (cell(p.x), cell(p.y), cell(p.z));
        let (c, row, slab) = (
            self.channels,
            self.res * self.channels,
            self.res * self.res * self.channels,
        );
        let base = ((iz * self.res + iy) * self.res + ix) * c;
        let d = &self.data;
        let along_x = |o: usize| d[o] + (d[o + c] - d[o]) * tx;
        let c0 = along_x(base) + (along_x(base + row) - along_x(base)) * ty;
        let c1 = along_x(base + slab) + (along_x(base + slab + row) - along_x(base + slab)) * ty;
        c0 + (c1 - c0) * tz
    }

    /// Grid points per axis.
    pub fn resolution(&self) -> usize {
        self.res
    }

    /// The 8 corners of the cell around `p` (clamped to the grid): their data offsets and
    /// trilinear weights.
    #[inline]
    fn corners(&self, p: &Vector3<f32>) -> ([usize; 8], [f32; 8]) {
        let scale = (self.res - 1) as f32 / (2.0 * self.bound);
        let max = (self.res - 1) as f32;
        let g = p.map(|c| ((c + self.bound) * scale).clamp(0.0, max));
        let i = g.map(|c| (c.floor() as usize).min(self.res - 2));
        let t = Vector3::new(g.x - i.x as f32, g.y - i.y as f32, g.z - i.z as f32);
        let mut offsets = [0usize; 8];
        let mut weights = [0f32; 8];
        for corner in 0..8 {
            let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, (corner >> 2) & 1);
            weights[corner] = if dx == 1 { t.x } else { 1.0 - t.x }
                * if dy == 1 { t.y } else { 1.0 - t.y }
                * if dz == 1 { t.z } else { 1.0 - t.z };
            offsets[corner] =
                (((i.z + dz) * self.res + (i.y + dy)) * self.res + (i.x + dx)) * self.channels;
        }
        (offsets, weights)
    }

    /// [`VoxelGrid::sample_into`] for a channel count known at compile time (the loops over
    /// channels unroll and vectorise: the trainer's targets are dominated by these lookups).
    #[inline]
    fn sample_fixed<const N: usize>(&self, p: &Vector3<f32>, out: &mut [f32]) {
        let (offsets, weights) = self.corners(p);
        let mut acc = [0f32; N];
        for (&o, &w) in offsets.iter().zip(&weights) {
            let v: &[f32; N] = self.data[o..o + N]
                .try_into()
                .expect("a corner holds `channels` values");
            for k in 0..N {
                acc[k] += w * v[k];
            }
        }
        out[..N].copy_from_slice(&acc);
    }

    /// Trilinear interpolation at `p` (clamped to the grid), written into `out` (`channels`).
    #[inline]
    pub fn sample_into(&self, p: &Vector3<f32>, out: &mut [f32]) {
        match self.channels {
            1 => return self.sample_fixed::<1>(p, out),
            12 => return self.sample_fixed::<12>(p, out),
            _ => {}
        }
        let c = self.channels;
        let (offsets, weights) = self.corners(p);
        out.iter_mut().for_each(|v| *v = 0.0);
        for (&o, &w) in offsets.iter().zip(&weights) {
            for (acc, v) in out.iter_mut().zip(&self.data[o..o + c]) {
                *acc += w * v;
            }
        }
    }

    /// Trilinear interpolation at many points, row-major `n × channels`.
    pub fn sample(&self, points: &[Vector3<f32>]) -> Vec<f32> {
        let mut out = vec![0.0; points.len() * self.channels];
        for (p, o) in points.iter().zip(out.chunks_mut(self.channels)) {
            self.sample_into(p, o);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_is_the_first_channel_of_the_trilinear_sample() {
        let grid = VoxelGrid::bake(7, 1.2, 2, |p| {
            p.iter()
                .flat_map(|q| [q.x * q.y - 0.3 * q.z * q.z + q.x, q.z])
                .collect()
        });
        for p in [
            Vector3::new(0.13, -0.71, 0.4),
            Vector3::new(1.19, 1.19, -1.19),
            Vector3::new(-3.0, 0.0, 2.5),
            Vector3::new(0.0, 0.0, 0.0),
        ] {
            let mut out = [0f32; 2];
            grid.sample_into(&p, &mut out);
            assert!((grid.value(&p) - out[0]).abs() < 1e-5, "{p:?}");
        }
    }

    #[test]
    fn trilinear_is_exact_for_affine_functions() {
        let f = |p: &[Vector3<f32>]| -> Vec<f32> {
            p.iter()
                .flat_map(|v| [2.0 * v.x - v.y + 0.5 * v.z + 1.0, v.z])
                .collect()
        };
        let grid = VoxelGrid::bake(9, 1.2, 2, f);
        for p in [
            Vector3::new(0.13f32, -0.7, 0.99),
            Vector3::new(-1.19, 1.1, 0.0),
            Vector3::new(0.0, 0.0, 0.0),
        ] {
            let got = grid.sample(&[p]);
            let want = f(&[p]);
            assert!((got[0] - want[0]).abs() < 1e-5 && (got[1] - want[1]).abs() < 1e-5);
        }
        // The fixed-width paths (1 and 12 channels) agree with the generic one.
        let wide = VoxelGrid::bake(7, 1.0, 12, |p| {
            p.iter()
                .flat_map(|v| (0..12).map(move |k| (k as f32 + 1.0) * v.x - v.y * v.z))
                .collect()
        });
        let p = Vector3::new(0.31f32, -0.42, 0.77);
        let mut fixed = [0f32; 12];
        wide.sample_into(&p, &mut fixed);
        let (offsets, weights) = wide.corners(&p);
        for (k, got) in fixed.iter().enumerate() {
            let generic: f32 = offsets
                .iter()
                .zip(&weights)
                .map(|(&o, &w)| w * wide.data[o + k])
                .sum();
            assert!((got - generic).abs() < 1e-5);
        }
        // Outside the grid the value is clamped to the boundary.
        let out = grid.sample(&[Vector3::new(5.0, 0.0, 0.0)]);
        assert!((out[0] - f(&[Vector3::new(1.2, 0.0, 0.0)])[0]).abs() < 1e-5);
    }
}
