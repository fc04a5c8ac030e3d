//! The fused head in bfloat16, for the coarse levels of a search: the same layers as
//! [`FusedHead`], with weights and every GEMM's input rounded to bfloat16 (round to nearest even)
//! and f32 accumulation. On a core with AVX-512 BF16 the GEMMs run on `VDPBF16PS` (two
//! multiply-adds per f32 lane, about twice the f32 FMA's rate); elsewhere the same rounding is
//! emulated on the f32 GEMM, so a search ranks the same cells on any machine (up to the order of
//! the f32 sums).
//!
//! The native kernel: weights packed once into column panels of [`NR`] columns, `[k-pair][column]
//! [2]`, so that one panel (256 inputs × 64 columns × 2 B = 32 KiB) stays in L1 while the rows of
//! a tile stream past it [`MR`] at a time; bias and ReLU are applied as each block leaves the
//! registers, and the last hidden layer goes straight into the `width → 1` dot product.

use super::fused::{Dense, FusedHead, Precision, Rows, TILE_ROWS, by_tiles};

/// Rows of the native kernel's register block.
pub const MR: usize = 6;
/// Columns of the native kernel's register block (four 16-lane vectors).
pub const NR: usize = 64;

/// `x` rounded to bfloat16 (round to nearest even, as `VCVTNEPS2BF16`), as its 16 bits.
pub fn to_bf16(x: f32) -> u16 {
    let bits = x.to_bits();
    if x.is_nan() {
        return ((bits >> 16) | 0x40) as u16;
    }
    let round = 0x7fff + ((bits >> 16) & 1);
    (bits.wrapping_add(round) >> 16) as u16
}

/// The f32 of a bfloat16's bits.
pub fn from_bf16(h: u16) -> f32 {
    f32::from_bits((h as u32) << 16)
}

/// `x` rounded to the nearest bfloat16.
pub fn round_bf16(x: f32) -> f32 {
    from_bf16(to_bf16(x))
}

/// The head in bfloat16: the native kernel where the core has it, the emulation elsewhere.
#[derive(Debug, Clone)]
pub enum Bf16Head {
    /// `VDPBF16PS` on packed weights.
    Native(Box<NativeHead>),
    /// The f32 GEMM on rounded weights, rounding each GEMM's input.
    Emulated(Box<FusedHead>),
}

impl Bf16Head {
    /// The native kernel when this core has AVX-512 BF16 (and every branch has a hidden layer),
    /// else the emulation.
    pub fn new(head: &FusedHead) -> Bf16Head {
        NativeHead::new(head)
            .map(|native| Bf16Head::Native(Box::new(native)))
            .unwrap_or_else(|| Bf16Head::emulated(head))
    }

    /// The emulation, on any core.
    pub fn emulated(head: &FusedHead) -> Bf16Head {
        Bf16Head::Emulated(Box::new(head.rounded_to_bf16()))
    }

    /// Whether this is the native kernel.
    pub fn is_native(&self) -> bool {
        matches!(self, Bf16Head::Native(_))
    }

    /// Both branches' log-weights of `rows`, as [`FusedHead::branch_scores_in`]. From encodings,
    /// the native kernel runs the rotation half of the first layer in bfloat16 too, inside the
    /// tiles (no projection pass).
    pub fn branch_scores(&self, image_term: &[f32], rows: Rows<'_>) -> (Vec<f32>, Vec<f32>) {
        match self {
            Bf16Head::Native(native) => native.branch_scores(image_term, rows),
            Bf16Head::Emulated(head) => head.branch_scores_in(Precision::F32, image_term, rows),
        }
    }
}

/// One layer's weights as bfloat16 column panels.
#[derive(Debug, Clone)]
struct Packed {
    /// Input pairs (inputs rounded up to even).
    pairs: usize,
    /// Column panels of [`NR`] (outputs rounded up).
    panels: usize,
    /// `[panel][pair][NR][2]` bfloat16 bits.
    weight: Vec<u16>,
    /// `[panels × NR]`, zero past the outputs.
    bias: Vec<f32>,
}

impl Packed {
    /// `dense`, taking `padded_inputs` inputs (≥ its own, even; the extra ones weigh zero).
    fn of(dense: &Dense, padded_inputs: usize) -> Packed {
        let pairs = padded_inputs / 2;
        let panels = dense.outputs.div_ceil(NR);
        let mut weight = vec![0u16; panels * pairs * NR * 2];
        for panel in 0..panels {
            for pair in 0..pairs {
                for c in 0..NR {
                    for t in 0..2 {
                        let (i, o) = (2 * pair + t, panel * NR + c);
                        if i < dense.inputs && o < dense.outputs {
                            weight[((panel * pairs + pair) * NR + c) * 2 + t] =
                                to_bf16(dense.weight[i * dense.outputs + o]);
                        }
                    }
                }
            }
        }
        let mut bias = dense.bias.clone();
        bias.resize(panels * NR, 0.0);
        Packed {
            pairs,
            panels,
            weight,
            bias,
        }
    }
}

/// One branch, packed.
#[derive(Debug, Clone)]
struct NativeBranch {
    hidden: Vec<Packed>,
    /// The output weights, zero-padded to the padded width.
    output: Vec<f32>,
    output_bias: f32,
}

/// The native kernel's head.
#[derive(Debug, Clone)]
pub struct NativeHead {
    width: usize,
    /// Width rounded up to [`NR`]: the stride of every activation row.
    padded: usize,
    /// The rotation half of the first layer (its bias included).
    rotation: Packed,
    /// Length of a rotation's encoding.
    encoding: usize,
    branches: [NativeBranch; 2],
}

/// One task's buffers: encodings, the shared input, two activation buffers (bfloat16), and the
/// output dot products.
struct Scratch {
    e: Vec<u16>,
    x: Vec<u16>,
    a: Vec<u16>,
    b: Vec<u16>,
    dots: Vec<f32>,
}

/// What leaves a GEMM's register block.
enum Epilogue<'a> {
    /// `relu(acc + b)` as bfloat16 rows of `stride`.
    Store { out: &'a mut [u16], stride: usize },
    /// `Σ_j relu(acc + b)_j · w_j` added to `dots[row]`.
    Dot {
        weights: &'a [f32],
        dots: &'a mut [f32],
    },
}

impl NativeHead {
    /// Packs `head`'s weights, or `None` when this core lacks AVX-512 BF16 or a branch has no
    /// hidden layer.
    pub fn new(head: &FusedHead) -> Option<NativeHead> {
        if !native_available() {
            return None;
        }
        let width = head.width();
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
            Some(NativeBranch {
                hidden: hidden.iter().map(|d| Packed::of(d, padded)).collect(),
                output,
                output_bias,
            })
        };
        let [shape, feature] = head.branch_layers();
        let rotation = head.rotation_layer();
        Some(NativeHead {
            width,
            padded,
            rotation: Packed::of(rotation, rotation.inputs.next_multiple_of(2)),
            encoding: rotation.inputs,
            branches: [branch(shape)?, branch(feature)?],
        })
    }

    /// Both branches' log-weights of `rows`.
    fn branch_scores(&self, image_term: &[f32], rows: Rows<'_>) -> (Vec<f32>, Vec<f32>) {
        let (given, per_row) = match rows {
            Rows::Projected(p) => (p, self.width),
            Rows::Encoded(e) => (e, self.encoding),
        };
        // The first layer's bias with the image's term in it, for encoded rows.
        let mut first_bias = self.rotation.bias.clone();
        for (b, i) in first_bias.iter_mut().zip(image_term) {
            *b += i;
        }
        let blocked = TILE_ROWS.div_ceil(MR) * MR;
        by_tiles(
            given,
            per_row,
            || Scratch {
                e: vec![0; blocked * 2 * self.rotation.pairs],
                x: vec![0; blocked * self.padded],
                a: vec![0; blocked * self.padded],
                b: vec![0; blocked * self.padded],
                dots: vec![0.0; blocked],
            },
            |scratch, given, out| {
                let tile = match rows {
                    Rows::Projected(_) => Rows::Projected(given),
                    Rows::Encoded(_) => Rows::Encoded(given),
                };
                self.tile(image_term, &first_bias, tile, scratch, out);
            },
        )
    }

    /// One tile of rows: the shared input `relu(P_R + W_I·f + b)`, then each branch.
    fn tile(
        &self,
        image_term: &[f32],
        first_bias: &[f32],
        given: Rows<'_>,
        scratch: &mut Scratch,
        out: [&mut [f32]; 2],
    ) {
        let stride = self.padded;
        let rows = out[0].len();
        let blocked = rows.div_ceil(MR) * MR;
        let Scratch { e, x, a, b, dots } = scratch;
        match given {
            Rows::Projected(projected) => {
                x[..blocked * stride].fill(0);
                let w = self.width;
                for (xr, pr) in x.chunks_exact_mut(stride).zip(projected.chunks_exact(w)) {
                    for ((xv, &p), &i) in xr.iter_mut().zip(pr).zip(image_term) {
                        *xv = to_bf16((p + i).max(0.0));
                    }
                }
            }
            Rows::Encoded(encodings) => {
                let e_stride = 2 * self.rotation.pairs;
                e[..blocked * e_stride].fill(0);
                for (er, enc) in e
                    .chunks_exact_mut(e_stride)
                    .zip(encodings.chunks_exact(self.encoding))
                {
                    for (ev, &v) in er.iter_mut().zip(enc) {
                        *ev = to_bf16(v);
                    }
                }
                let epilogue = Epilogue::Store { out: x, stride };
                // SAFETY: `native_available()` held when this head was built; `e` holds
                // `blocked` rows of `e_stride` = 2 × pairs, `x` `blocked` rows of `stride` ≥ the
                // layer's panels × NR, and `first_bias` as many values.
                unsafe { gemm_bf16(&self.rotation, first_bias, e, e_stride, blocked, epilogue) };
            }
        }
        for (branch, out) in self.branches.iter().zip(out) {
            let last = branch.hidden.len() - 1;
            let dots = &mut dots[..blocked];
            dots.fill(branch.output_bias);
            for (l, layer) in branch.hidden.iter().enumerate() {
                // Layer l reads x (l = 0), a (odd l) or b, and writes the other of a and b.
                let (input, output) = match l {
                    0 => (&x[..], &mut a[..]),
                    l if l % 2 == 1 => (&a[..], &mut b[..]),
                    _ => (&b[..], &mut a[..]),
                };
                let epilogue = if l == last {
                    Epilogue::Dot {
                        weights: &branch.output,
                        dots: &mut *dots,
                    }
                } else {
                    Epilogue::Store {
                        out: output,
                        stride,
                    }
                };
                // SAFETY: as above; `input` holds `blocked` rows of `stride` = 2 × the layer's
                // pairs, and the epilogue's buffers hold `blocked` rows.
                unsafe { gemm_bf16(layer, &layer.bias, input, stride, blocked, epilogue) };
            }
            out.copy_from_slice(&dots[..rows]);
        }
    }
}

/// Whether this core runs the native kernel.
pub fn native_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn gemm_bf16(_: &Packed, _: &[f32], _: &[u16], _: usize, _: usize, _: Epilogue<'_>) {
    unreachable!("the native kernel is only built on x86_64")
}

/// `relu(input · W + bias)` for `rows` (a multiple of [`MR`]) rows of `input` (bfloat16, rows of
/// `stride`), through `epilogue`.
///
/// # Safety
/// The core has AVX-512F and AVX-512 BF16; `bias` holds `layer.panels × NR` values; `input`
/// holds `rows × stride` values with `stride ≥ 2 × layer.pairs`; a `Store` output holds `rows`
/// rows of its stride, which is at least `layer.panels × NR`; a `Dot`'s `dots` hold `rows` and its
/// weights `layer.panels × NR`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn gemm_bf16(
    layer: &Packed,
    bias: &[f32],
    input: &[u16],
    stride: usize,
    rows: usize,
    epilogue: Epilogue<'_>,
) {
    use std::arch::x86_64::*;
    debug_assert!(
        rows.is_multiple_of(MR)
            && input.len() >= rows * stride
            && stride >= 2 * layer.pairs
            && bias.len() >= layer.panels * NR
    );
    let pairs = layer.pairs;
    let mut epilogue = epilogue;
    for panel in 0..layer.panels {
        // SAFETY (all pointer reads and writes below): within the bounds stated above.
        unsafe {
            let weights = layer.weight.as_ptr().add(panel * pairs * NR * 2);
            let bias: [__m512; 4] =
                std::array::from_fn(|c| _mm512_loadu_ps(bias.as_ptr().add(panel * NR + 16 * c)));
            for r0 in (0..rows).step_by(MR) {
                let mut acc = [[_mm512_setzero_ps(); 4]; MR];
                let a = input.as_ptr().add(r0 * stride);
                for pair in 0..pairs {
                    let w = weights.add(pair * NR * 2);
                    let b: [__m512bh; 4] = std::array::from_fn(|c| {
                        std::mem::transmute(_mm512_loadu_si512(w.add(32 * c) as *const _))
                    });
                    for (r, acc) in acc.iter_mut().enumerate() {
                        let pair_bits =
                            (a.add(r * stride + 2 * pair) as *const i32).read_unaligned();
                        let x: __m512bh = std::mem::transmute(_mm512_set1_epi32(pair_bits));
                        for c in 0..4 {
                            acc[c] = _mm512_dpbf16_ps(acc[c], x, b[c]);
                        }
                    }
                }
                let zero = _mm512_setzero_ps();
                for (r, acc) in acc.iter().enumerate() {
                    let row = r0 + r;
                    let h: [__m512; 4] = std::array::from_fn(|c| {
                        _mm512_max_ps(_mm512_add_ps(acc[c], bias[c]), zero)
                    });
                    match &mut epilogue {
                        Epilogue::Store { out, stride } => {
                            let o = out.as_mut_ptr().add(row * *stride + panel * NR);
                            for (c, h) in h.iter().enumerate() {
                                let packed: __m256i = std::mem::transmute(_mm512_cvtneps_pbh(*h));
                                _mm256_storeu_si256(o.add(16 * c) as *mut __m256i, packed);
                            }
                        }
                        Epilogue::Dot { weights, dots } => {
                            let wo = weights.as_ptr().add(panel * NR);
                            let mut sum = _mm512_mul_ps(h[0], _mm512_loadu_ps(wo));
                            for (c, h) in h.iter().enumerate().skip(1) {
                                sum = _mm512_fmadd_ps(*h, _mm512_loadu_ps(wo.add(16 * c)), sum);
                            }
                            dots[row] += _mm512_reduce_add_ps(sum);
                        }
                    }
                }
            }
        }
    }
}
