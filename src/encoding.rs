//! Positional encodings of rotations, the input of the distribution head (docs/DESIGN.md §2).
//!
//! Both take rotations as row-major `f32` matrices (`[r00, r01, …, r22]`) and return one row per
//! rotation, either as plain `Vec<f32>` rows (row-major `n × dim`) or as a burn tensor `[n, dim]`.

use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

/// Frequencies of the cube encoding: `2^k`, `k = 0, 1, 2` (paper, supplementary: "3 frequencies").
pub const CUBE_FREQUENCIES: usize = 3;

/// Length of the cube encoding: 8 vertices × 3 coordinates × 3 frequencies × (sin, cos) = 144.
pub const CUBE_ENCODING_DIM: usize = 8 * 3 * CUBE_FREQUENCIES * 2;

/// The cube's vertices `(±1, ±1, ±1)` in a fixed order (x slowest).
const CUBE_VERTICES: [[f32; 3]; 8] = [
    [-1.0, -1.0, -1.0],
    [-1.0, -1.0, 1.0],
    [-1.0, 1.0, -1.0],
    [-1.0, 1.0, 1.0],
    [1.0, -1.0, -1.0],
    [1.0, -1.0, 1.0],
    [1.0, 1.0, -1.0],
    [1.0, 1.0, 1.0],
];

/// Which positional encoding a network uses.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum RotationEncoding {
    /// The paper's cube encoding ([`cube_encoding`]), the default.
    #[default]
    Cube,
    /// IPDF's encoding of the matrix entries ([`ipdf_encoding`]) with this many frequencies.
    Ipdf {
        /// Number of frequencies `2^0 … 2^(nf−1)`.
        frequencies: usize,
    },
}

impl RotationEncoding {
    /// Length of one encoded rotation.
    pub fn dim(&self) -> usize {
        match *self {
            RotationEncoding::Cube => CUBE_ENCODING_DIM,
            RotationEncoding::Ipdf { frequencies } => 9 * frequencies * 2,
        }
    }

    /// Encodes a batch, row-major `n × dim`.
    pub fn encode(&self, rotations: &[[f32; 9]]) -> Vec<f32> {
        match *self {
            RotationEncoding::Cube => cube_encoding(rotations),
            RotationEncoding::Ipdf { frequencies } => ipdf_encoding(rotations, frequencies),
        }
    }

    /// Encodes a batch as a tensor `[n, dim]` on `device`.
    pub fn encode_tensor(&self, rotations: &[[f32; 9]], device: &Device) -> Tensor<2> {
        let rows = self.encode(rotations);
        Tensor::from_data(TensorData::new(rows, [rotations.len(), self.dim()]), device)
    }
}

/// The paper's cube positional encoding (Sec. 3.3, "Positional encoding (PE)"; supplementary):
/// rotate the 8 vertices `v_c = (±1, ±1, ±1)` by `R`, then for each frequency `f = 2^k`
/// (`k = 0, 1, 2`) emit `sin(f · R v_c)` for the 24 rotated coordinates followed by
/// `cos(f · R v_c)`. Row layout: `[sin f₀ (24), cos f₀ (24), sin f₁ (24), …]`, 144 values.
pub fn cube_encoding(rotations: &[[f32; 9]]) -> Vec<f32> {
    use rayon::prelude::*;
    let mut out = vec![0f32; rotations.len() * CUBE_ENCODING_DIM];
    out.par_chunks_mut(ENCODE_CHUNK * CUBE_ENCODING_DIM)
        .zip(rotations.par_chunks(ENCODE_CHUNK))
        .for_each(|(out, rotations)| {
            for (row, m) in out.chunks_exact_mut(CUBE_ENCODING_DIM).zip(rotations) {
                cube_row(m, row);
            }
        });
    out
}

/// Rotations per task of [`cube_encoding`] (spread over the cores).
const ENCODE_CHUNK: usize = 512;

/// One row of [`cube_encoding`]: `sin` and `cos` of the 24 rotated coordinates at frequency 1,
/// then each higher frequency from the one below by the double-angle formulas
/// (`sin 2x = 2 sin x cos x`, `cos 2x = (cos x − sin x)(cos x + sin x)`), a third of the calls
/// to `sin`/`cos`, within a few 1e-7 of them.
fn cube_row(m: &[f32; 9], row: &mut [f32]) {
    let (mut sin, mut cos) = ([0f32; 24], [0f32; 24]);
    for (v, vertex) in CUBE_VERTICES.iter().enumerate() {
        for r in 0..3 {
            let x = m[r * 3] * vertex[0] + m[r * 3 + 1] * vertex[1] + m[r * 3 + 2] * vertex[2];
            (sin[v * 3 + r], cos[v * 3 + r]) = x.sin_cos();
        }
    }
    for (k, out) in row.chunks_exact_mut(48).enumerate() {
        if k > 0 {
            for (s, c) in sin.iter_mut().zip(cos.iter_mut()) {
                (*s, *c) = (2.0 * *s * *c, (*c - *s) * (*c + *s));
            }
        }
        out[..24].copy_from_slice(&sin);
        out[24..].copy_from_slice(&cos);
    }
}

/// IPDF's positional encoding (Murphy et al. 2021): for each frequency `f = 2^k`
/// (`k = 0 … nf−1`), `sin(f · r_ij)` for the 9 row-major entries followed by `cos(f · r_ij)`.
/// Row layout `[sin f₀ (9), cos f₀ (9), sin f₁ (9), …]`, `18·nf` values.
pub fn ipdf_encoding(rotations: &[[f32; 9]], frequencies: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(rotations.len() * 18 * frequencies);
    for m in rotations {
        push_fourier(&mut out, m, frequencies);
    }
    out
}

/// Appends `[sin(2^k x), cos(2^k x)]` for `k = 0 … nf−1`.
fn push_fourier(out: &mut Vec<f32>, values: &[f32], frequencies: usize) {
    for k in 0..frequencies {
        let f = (1u32 << k) as f32;
        out.extend(values.iter().map(|&x| (f * x).sin()));
        out.extend(values.iter().map(|&x| (f * x).cos()));
    }
}

/// [`cube_encoding`] as a tensor `[n, 144]`.
pub fn cube_encoding_tensor(rotations: &[[f32; 9]], device: &Device) -> Tensor<2> {
    RotationEncoding::Cube.encode_tensor(rotations, device)
}

/// [`ipdf_encoding`] as a tensor `[n, 18·nf]`.
pub fn ipdf_encoding_tensor(
    rotations: &[[f32; 9]],
    frequencies: usize,
    device: &Device,
) -> Tensor<2> {
    RotationEncoding::Ipdf { frequencies }.encode_tensor(rotations, device)
}
