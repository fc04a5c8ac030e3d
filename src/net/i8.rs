//! The fused head in 8-bit integers, for the coarse levels of a search on cores with AVX-512
//! VNNI. `VPDPBUSD` multiplies 64 unsigned by 64 signed bytes and adds them four by four into
//! 16 i32 lanes: at the f32 FMA's instruction rate, four times its arithmetic (twice f16's).
//!
//! What is rounded, and how ([`super::tiles`]):
//! - each layer's weights to signed bytes with one scale per output column
//!   ([`columns_to_i8`]: the column's largest |w| is 127);
//! - each row of activations (ReLU outputs, never negative) to unsigned bytes with the row's own
//!   scale ([`row_to_u8`]: the row's maximum is 255), so a row of small values keeps its
//!   resolution;
//! - encodings (sines and cosines) to a fixed grid of [−1, 1] ([`encoding_to_u8`]:
//!   `u = (e + 1)·127.5`); the offset is folded into the first layer's bias.
//!
//! The integer sums are exact; each block leaves the registers as `relu(acc · s_row · s_col + b)`
//! in f32, and a layer's rows are rounded to bytes again once all their columns are out (a row's
//! scale needs its maximum). The branches' last hidden layer feeds the f32 output dot product.
//! Elsewhere the same rounding is emulated on the f32 GEMM (`FusedHead`'s emulation), so a
//! search ranks the same cells on any machine, up to the order of the f32 sums.

use super::dense::Dense;
use super::native::{Epilogue, Packed};
use super::tiles::{
    ENCODING_SCALE, Rows, TILE_ROWS, by_tiles, columns_to_i8, encoding_to_u8, row_to_u8,
};
use super::weights::HeadWeights;

/// Rows of the kernel's register block.
pub const MR: usize = 6;
/// Columns of the kernel's register block (four 16-lane vectors).
pub const NR: usize = 64;
/// Inputs per 32-bit lane of `VPDPBUSD`.
const GROUP: usize = 4;

/// Whether this core runs the native kernel.
pub fn native_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512bw")
            && std::is_x86_feature_detected!("avx512vnni")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// One layer in bytes: weights packed `[panel][group][NR][4]`, the bias in `packed.bias`, and
/// each column's scale.
#[derive(Debug, Clone)]
struct I8Layer {
    packed: Packed<u8>,
    /// `[panels × NR]`, zero past the outputs.
    scales: Vec<f32>,
}

impl I8Layer {
    /// `dense` in bytes, taking `padded_inputs` inputs (a multiple of 4; the extra ones weigh 0).
    fn of(dense: &Dense, padded_inputs: usize) -> (I8Layer, Vec<i8>) {
        let (bytes, mut scales) = columns_to_i8(&dense.weight, dense.outputs);
        let as_values = Dense {
            weight: bytes.iter().map(|&b| b as f32).collect(),
            ..dense.clone()
        };
        let packed = Packed::of(&as_values, padded_inputs, (GROUP, NR), |v| v as i8 as u8);
        scales.resize(packed.panels * NR, 0.0);
        (I8Layer { packed, scales }, bytes)
    }

    /// The rotation layer, reading encodings as `u = (e + 1)·127.5`:
    /// `Σ_i w_ij e_i = s_j · (Σ_i q_ij u_i) / 127.5 − s_j · Σ_i q_ij`; the second term joins the
    /// bias, the first's `1/127.5` is every row's scale.
    fn of_encoding(dense: &Dense, padded_inputs: usize) -> I8Layer {
        let (mut layer, bytes) = I8Layer::of(dense, padded_inputs);
        for (j, bias) in layer.packed.bias[..dense.outputs].iter_mut().enumerate() {
            let column: i32 = bytes
                .iter()
                .skip(j)
                .step_by(dense.outputs)
                .map(|&q| q as i32)
                .sum();
            *bias -= layer.scales[j] * column as f32;
        }
        layer
    }
}

/// One branch in bytes.
#[derive(Debug, Clone)]
struct I8Branch {
    hidden: Vec<I8Layer>,
    /// The output weights, zero-padded to the padded width.
    output: Vec<f32>,
    output_bias: f32,
}

/// The head on the 8-bit kernel.
#[derive(Debug, Clone)]
pub(super) struct I8Head {
    width: usize,
    /// Width rounded up to [`NR`]: the stride of every activation row.
    padded: usize,
    rotation: I8Layer,
    /// Length of a rotation's encoding.
    encoding: usize,
    branches: [I8Branch; 2],
}

/// One task's buffers: one f32 row, the encodings, a layer's f32 outputs, three byte buffers
/// (the shared input and two for the layers) with their rows' scales, and the output dots.
struct Scratch {
    row: Vec<f32>,
    e: Vec<u8>,
    /// Every encoded row's scale, `1/127.5`.
    e_scales: Vec<f32>,
    out: Vec<f32>,
    bytes: [Vec<u8>; 3],
    scales: [Vec<f32>; 3],
    dots: Vec<f32>,
}

impl I8Head {
    /// Packs `head`'s weights in bytes, or `None` when this core lacks AVX-512 VNNI or a branch
    /// has no hidden layer (or one of another width).
    pub(super) fn new(head: &HeadWeights) -> Option<I8Head> {
        if !native_available() {
            return None;
        }
        let width = head.width;
        let padded = width.div_ceil(NR) * NR;
        let branch = |(hidden, output, output_bias): (&[Dense], &[f32], f32)| {
            if hidden.is_empty()
                || hidden
                    .iter()
                    .any(|d| d.inputs != width || d.outputs != width)
            {
                return None;
            }
            let mut output = output.to_vec();
            output.resize(padded, 0.0);
            Some(I8Branch {
                hidden: hidden.iter().map(|d| I8Layer::of(d, padded).0).collect(),
                output,
                output_bias,
            })
        };
        let [shape, feature] = head.branch_layers();
        let rotation = &head.rotation;
        Some(I8Head {
            width,
            padded,
            rotation: I8Layer::of_encoding(rotation, rotation.inputs.next_multiple_of(GROUP)),
            encoding: rotation.inputs,
            branches: [branch(shape)?, branch(feature)?],
        })
    }

    /// Both branches' log-weights of `rows`, for one image's term of the first layer.
    pub(super) fn branch_scores(&self, image_term: &[f32], rows: Rows<'_>) -> (Vec<f32>, Vec<f32>) {
        let (given, per_row) = match rows {
            Rows::Projected(p) => (p, self.width),
            Rows::Encoded(e) => (e, self.encoding),
        };
        let mut first_bias = self.rotation.packed.bias.clone();
        for (b, i) in first_bias.iter_mut().zip(image_term) {
            *b += i;
        }
        let blocked = TILE_ROWS.div_ceil(MR) * MR;
        let e_stride = GROUP * self.rotation.packed.groups;
        by_tiles(
            given,
            per_row,
            || Scratch {
                row: vec![0.0; self.width],
                e: vec![0; blocked * e_stride],
                e_scales: vec![1.0 / ENCODING_SCALE; blocked],
                out: vec![0.0; blocked * self.padded],
                bytes: std::array::from_fn(|_| vec![0; blocked * self.padded]),
                scales: std::array::from_fn(|_| vec![0.0; blocked]),
                dots: vec![0.0; blocked],
            },
            |scratch, given, out| {
                let tile = match rows {
                    Rows::Projected(_) => Rows::Projected(given),
                    Rows::Encoded(_) => Rows::Encoded(given),
                };
                // SAFETY: `new` checked the core's features.
                unsafe { self.tile(image_term, &first_bias, tile, scratch, out) };
            },
        )
    }

    /// One tile of rows: the shared input `relu(P_R + W_I·f + b)` in bytes, then each branch.
    /// Compiled for AVX-512, so that the rounding of rows to bytes between the GEMMs is
    /// vectorised to the kernel's width (narrower, it cost more than the GEMMs).
    ///
    /// # Safety
    /// The core has AVX-512F, BW and VNNI (an `I8Head` is only built on such a core).
    #[cfg_attr(
        target_arch = "x86_64",
        target_feature(enable = "avx512f,avx512bw,avx512vnni")
    )]
    unsafe fn tile(
        &self,
        image_term: &[f32],
        first_bias: &[f32],
        given: Rows<'_>,
        scratch: &mut Scratch,
        out: [&mut [f32]; 2],
    ) {
        let (w, stride) = (self.width, self.padded);
        let rows = out[0].len();
        let blocked = rows.div_ceil(MR) * MR;
        let Scratch {
            row,
            e,
            e_scales,
            out: values,
            bytes: [x, a, b],
            scales: [sx, sa, sb],
            dots,
        } = scratch;
        match given {
            Rows::Projected(projected) => {
                x[..blocked * stride].fill(0);
                sx[..blocked].fill(0.0);
                for (r, pr) in projected.chunks_exact(w).enumerate() {
                    for ((v, &p), &i) in row.iter_mut().zip(pr).zip(image_term) {
                        *v = (p + i).max(0.0);
                    }
                    sx[r] = row_bytes(row, &mut x[r * stride..r * stride + w]);
                }
            }
            Rows::Encoded(encodings) => {
                let e_stride = GROUP * self.rotation.packed.groups;
                e[..blocked * e_stride].fill(0);
                for (er, enc) in e
                    .chunks_exact_mut(e_stride)
                    .zip(encodings.chunks_exact(self.encoding))
                {
                    encoding_bytes(enc, er);
                }
                let store = Epilogue::Store {
                    out: values,
                    stride,
                };
                // SAFETY: the core has the kernel's features (checked in `new`); `e` holds
                // `blocked` rows of `e_stride` = 4 × groups, `e_scales` and the output
                // `blocked` rows, `first_bias` the layer's panels × NR values.
                unsafe {
                    gemm(
                        &self.rotation,
                        first_bias,
                        e,
                        e_scales,
                        e_stride,
                        blocked,
                        store,
                    )
                };
                rows_to_u8(values, x, sx, blocked, (w, stride));
            }
        }
        for (branch, out) in self.branches.iter().zip(out) {
            let last = branch.hidden.len() - 1;
            let dots = &mut dots[..blocked];
            dots.fill(branch.output_bias);
            for (l, layer) in branch.hidden.iter().enumerate() {
                // Layer l reads x (l = 0), a (odd l) or b, and writes the other of a and b.
                let (input, in_scales, output, out_scales) = match l {
                    0 => (&x[..], &sx[..], &mut a[..], &mut sa[..]),
                    l if l % 2 == 1 => (&a[..], &sa[..], &mut b[..], &mut sb[..]),
                    _ => (&b[..], &sb[..], &mut a[..], &mut sa[..]),
                };
                let bias = &layer.packed.bias;
                if l == last {
                    let dot = Epilogue::Dot {
                        weights: &branch.output,
                        dots: &mut *dots,
                    };
                    // SAFETY: as above; `input` holds `blocked` rows of `stride`.
                    unsafe { gemm(layer, bias, input, in_scales, stride, blocked, dot) };
                } else {
                    let store = Epilogue::Store {
                        out: &mut values[..],
                        stride,
                    };
                    // SAFETY: as above.
                    unsafe { gemm(layer, bias, input, in_scales, stride, blocked, store) };
                    rows_to_u8(values, output, out_scales, blocked, (w, stride));
                }
            }
            out.copy_from_slice(&dots[..rows]);
        }
    }
}

/// The first `rows` rows of `values` (`width` values each, rows `stride` apart) in bytes on
/// their own grids ([`row_to_u8`]), into `bytes` and `scales`.
#[inline(always)]
fn rows_to_u8(
    values: &[f32],
    bytes: &mut [u8],
    scales: &mut [f32],
    rows: usize,
    (width, stride): (usize, usize),
) {
    for (r, scale) in scales[..rows].iter_mut().enumerate() {
        let at = r * stride;
        *scale = row_bytes(&values[at..at + width], &mut bytes[at..at + width]);
    }
}

/// [`encoding_to_u8`] of each of `src` into `dst`, 16 values per instruction where the length
/// allows (the same clamp and product, rounded to nearest even by `VCVTPS2UDQ`).
#[inline(always)]
fn encoding_bytes(src: &[f32], dst: &mut [u8]) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if native_available() {
        done = src.len().min(dst.len()) / 16 * 16;
        // SAFETY: the features were checked; both slices hold `done` values.
        unsafe { encoding_bytes_avx512(&src[..done], &mut dst[..done]) };
    }
    for (d, &e) in dst.iter_mut().zip(src).skip(done) {
        *d = encoding_to_u8(e);
    }
}

/// # Safety
/// The core has AVX-512F; `src.len()` is a multiple of 16 and at most `dst.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn encoding_bytes_avx512(src: &[f32], dst: &mut [u8]) {
    use std::arch::x86_64::*;
    let (one, two) = (_mm512_set1_ps(1.0), _mm512_set1_ps(2.0));
    let (zero, scale) = (_mm512_setzero_ps(), _mm512_set1_ps(ENCODING_SCALE));
    for (v, d) in src.chunks_exact(16).zip(dst.chunks_exact_mut(16)) {
        // SAFETY: 16 floats read, 16 bytes written.
        unsafe {
            let e = _mm512_add_ps(_mm512_loadu_ps(v.as_ptr()), one);
            let u = _mm512_mul_ps(_mm512_min_ps(_mm512_max_ps(e, zero), two), scale);
            let bytes = _mm512_cvtepi32_epi8(_mm512_cvtps_epu32(u));
            _mm_storeu_si128(d.as_mut_ptr() as *mut __m128i, bytes);
        }
    }
}

/// [`row_to_u8`], 16 values per instruction where the width allows: the same maximum, the same
/// products, rounded to nearest even by `VCVTPS2UDQ` as by the scalar version.
#[inline(always)]
fn row_bytes(src: &[f32], dst: &mut [u8]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if src.len().is_multiple_of(16) && dst.len() >= src.len() && native_available() {
        // SAFETY: the features were checked; `src` holds whole vectors, `dst` as many bytes.
        return unsafe { row_bytes_avx512(src, dst) };
    }
    row_to_u8(src, dst)
}

/// # Safety
/// The core has AVX-512F; `src.len()` is a multiple of 16 and at most `dst.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn row_bytes_avx512(src: &[f32], dst: &mut [u8]) -> f32 {
    use std::arch::x86_64::*;
    // SAFETY: whole vectors of `src` read, as many bytes of `dst` written.
    unsafe {
        let mut max = _mm512_setzero_ps();
        for v in src.chunks_exact(16) {
            max = _mm512_max_ps(_mm512_loadu_ps(v.as_ptr()), max);
        }
        let max = _mm512_reduce_max_ps(max);
        if !(max > 0.0 && max.is_finite()) {
            return row_to_u8(src, dst);
        }
        let inverse = _mm512_set1_ps(255.0 / max);
        let (low, high) = (_mm512_setzero_ps(), _mm512_set1_ps(255.0));
        for (v, d) in src.chunks_exact(16).zip(dst.chunks_exact_mut(16)) {
            let x = _mm512_mul_ps(_mm512_loadu_ps(v.as_ptr()), inverse);
            let x = _mm512_min_ps(_mm512_max_ps(x, low), high);
            let bytes = _mm512_cvtepi32_epi8(_mm512_cvtps_epu32(x));
            _mm_storeu_si128(d.as_mut_ptr() as *mut __m128i, bytes);
        }
        max / 255.0
    }
}

/// `relu(acc · s_row · s_col + b)` of `rows` rows of `input` (bytes, rows of `stride`, each
/// with its scale in `row_scales`) times `layer`, through `epilogue`: the GEMM on `VPDPBUSD`.
///
/// # Safety
/// The core has AVX-512F, BW and VNNI (when it does not, this is never called); `rows` is a
/// multiple of [`MR`]; `input` holds `rows × stride` bytes with `stride ≥ 4 × groups`;
/// `row_scales` `rows` values; `bias` the layer's `panels × NR`; a `Store` output holds `rows`
/// rows of its stride (≥ panels × NR), a `Dot` `rows` dots and `panels × NR` weights.
unsafe fn gemm(
    layer: &I8Layer,
    bias: &[f32],
    input: &[u8],
    row_scales: &[f32],
    stride: usize,
    rows: usize,
    epilogue: Epilogue<'_, f32>,
) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the caller's contract is the kernel's.
    unsafe {
        gemm_vnni(layer, bias, input, row_scales, stride, rows, epilogue)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (layer, bias, input, row_scales, stride, rows, epilogue);
        unreachable!("the native kernels are only built on x86_64")
    }
}

/// [`gemm`] on AVX-512 VNNI: blocks of 6 rows × 64 columns, 24 i32 accumulators; each row's
/// four bytes of a group broadcast from the row, the weights' 64 bytes of a group and column
/// vector loaded once per block row set.
///
/// # Safety
/// As [`gemm`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn gemm_vnni(
    layer: &I8Layer,
    bias: &[f32],
    input: &[u8],
    row_scales: &[f32],
    stride: usize,
    rows: usize,
    epilogue: Epilogue<'_, f32>,
) {
    use std::arch::x86_64::*;
    let packed = &layer.packed;
    debug_assert!(
        rows.is_multiple_of(MR)
            && input.len() >= rows * stride
            && stride >= GROUP * packed.groups
            && row_scales.len() >= rows
            && bias.len() >= packed.panels * NR
    );
    let groups = packed.groups;
    let mut epilogue = epilogue;
    for panel in 0..packed.panels {
        // SAFETY (all pointer reads and writes below): within the bounds stated above.
        unsafe {
            let weights = packed.weight.as_ptr().add(panel * groups * NR * GROUP);
            let at = |v: &[f32], c: usize| _mm512_loadu_ps(v.as_ptr().add(panel * NR + 16 * c));
            let bias: [__m512; 4] = std::array::from_fn(|c| at(bias, c));
            let scale: [__m512; 4] = std::array::from_fn(|c| at(&layer.scales, c));
            for r0 in (0..rows).step_by(MR) {
                let mut acc = [[_mm512_setzero_si512(); 4]; MR];
                let a = input.as_ptr().add(r0 * stride);
                for g in 0..groups {
                    let w = weights.add(g * NR * GROUP);
                    let b: [__m512i; 4] =
                        std::array::from_fn(|c| _mm512_loadu_si512(w.add(64 * c) as *const _));
                    for (r, acc) in acc.iter_mut().enumerate() {
                        let four = (a.add(r * stride + GROUP * g) as *const i32).read_unaligned();
                        let x = _mm512_set1_epi32(four);
                        for c in 0..4 {
                            acc[c] = _mm512_dpbusd_epi32(acc[c], x, b[c]);
                        }
                    }
                }
                let zero = _mm512_setzero_ps();
                for (r, acc) in acc.iter().enumerate() {
                    let row = r0 + r;
                    let s = _mm512_set1_ps(row_scales[row]);
                    let h: [__m512; 4] = std::array::from_fn(|c| {
                        let sum = _mm512_cvtepi32_ps(acc[c]);
                        _mm512_max_ps(
                            _mm512_fmadd_ps(sum, _mm512_mul_ps(scale[c], s), bias[c]),
                            zero,
                        )
                    });
                    match &mut epilogue {
                        Epilogue::Store { out, stride } => {
                            let o = out.as_mut_ptr().add(row * *stride + panel * NR);
                            for (c, h) in h.iter().enumerate() {
                                _mm512_storeu_ps(o.add(16 * c), *h);
                            }
                        }
                        Epilogue::Dot { weights, dots } => {
                            dots[row] += super::native::dot4(&h, weights.as_ptr().add(panel * NR));
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vector rounding of a row (and of encodings) to bytes gives the scalar one's bytes, ties (a
    /// product exactly halfway between two bytes) included, and so does a row of zeros.
    #[test]
    fn rows_round_to_the_same_bytes_in_vectors_as_in_scalars() {
        let mut rows: Vec<Vec<f32>> = (0..20)
            .map(|r| {
                (0..64)
                    .map(|i| (((i * 37 + r * 11) % 23) as f32 * 0.37 - 2.0).max(0.0))
                    .collect()
            })
            .collect();
        // Steps of 1 up to the maximum 255, and halves between them: ties.
        rows.push((0..64).map(|i| (i % 32) as f32 * 0.5).collect::<Vec<f32>>());
        rows.last_mut().unwrap()[63] = 255.0;
        rows.push(vec![0.0; 64]);
        for row in &rows {
            let (mut vector, mut scalar) = ([0u8; 64], [0u8; 64]);
            let step = row_bytes(row, &mut vector);
            assert_eq!(step, row_to_u8(row, &mut scalar));
            assert_eq!(vector, scalar, "{row:?}");
        }
        // Encodings: every value of [−1, 1] in steps that fall on and between the bytes.
        let encodings: Vec<f32> = (0..=1020).map(|i| i as f32 / 510.0 - 1.0).collect();
        let (mut vector, mut scalar) = (vec![0u8; 1021], vec![0u8; 1021]);
        encoding_bytes(&encodings, &mut vector);
        for (s, &e) in scalar.iter_mut().zip(&encodings) {
            *s = encoding_to_u8(e);
        }
        assert_eq!(vector, scalar);
        let mut bytes = [0u8; 64];
        row_bytes(&rows[20], &mut bytes);
        // 0.5 → 0, 1.5 → 2, 2.5 → 2: to even, as VCVTPS2UDQ rounds.
        assert_eq!((bytes[1], bytes[3], bytes[5]), (0, 2, 2));
    }

    /// A column's largest |w| is ±127 and the rest keep their ratio to it within half a step.
    #[test]
    fn each_column_has_its_own_scale() {
        // Two columns, the second a thousand times larger than the first.
        let weight = [0.5, 400.0, -1.0, 250.0, 0.25, -1000.0];
        let (bytes, scales) = columns_to_i8(&weight, 2);
        assert_eq!(bytes, [64, 51, -127, 32, 32, -127]);
        assert_eq!(scales, [1.0 / 127.0, 1000.0 / 127.0]);
    }
}
