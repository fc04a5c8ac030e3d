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

    /// Number of values per grid point.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Grid points per axis.
    pub fn resolution(&self) -> usize {
        self.res
    }

    /// Trilinear interpolation at `p` (clamped to the grid), written into `out` (`channels`).
    #[inline]
    pub fn sample_into(&self, p: &Vector3<f32>, out: &mut [f32]) {
        let scale = (self.res - 1) as f32 / (2.0 * self.bound);
        let max = (self.res - 1) as f32;
        let g = p.map(|c| ((c + self.bound) * scale).clamp(0.0, max));
        let i = g.map(|c| (c.floor() as usize).min(self.res - 2));
        let t = Vector3::new(g.x - i.x as f32, g.y - i.y as f32, g.z - i.z as f32);
        let c = self.channels;
        out.iter_mut().for_each(|v| *v = 0.0);
        for corner in 0..8 {
            let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, (corner >> 2) & 1);
            let w = if dx == 1 { t.x } else { 1.0 - t.x }
                * if dy == 1 { t.y } else { 1.0 - t.y }
                * if dz == 1 { t.z } else { 1.0 - t.z };
            let idx = (((i.z + dz) * self.res + (i.y + dy)) * self.res + (i.x + dx)) * c;
            for (o, v) in out.iter_mut().zip(&self.data[idx..idx + c]) {
                *o += w * v;
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
        // Outside the grid the value is clamped to the boundary.
        let out = grid.sample(&[Vector3::new(5.0, 0.0, 0.0)]);
        assert!((out[0] - f(&[Vector3::new(1.2, 0.0, 0.0)])[0]).abs() < 1e-5);
    }
}
