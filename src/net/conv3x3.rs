//! A 3 × 3 convolution at padding 1 and stride 1 or 2 computed directly from the image, without
//! im2col's columns: for serving's batch of one, where im2col's matrix of the 64 px encoder's
//! first stage (144 rows × 4 096 pixels, 2.4 MB) is written, then packed again by the GEMM,
//! larger than the core's L2, while the image it comes from (16 planes of 66 × 66, 279 kB)
//! and the output stay in it.
//!
//! The image is copied once, zero-padded, into a buffer a block reads with plain unaligned
//! loads: at stride 1 the padded planes; at stride 2 each padded row split into its even and its
//! odd columns, side by side, so that taps `dx` = 0, 1, 2 of eight neighbouring outputs are eight
//! consecutive values (even columns from `ox`, odd from `ox`, even from `ox + 1`).
//!
//! Each output row is computed in blocks of channels × pixels whose accumulators stay in eight
//! vector registers (AVX-512: 8 channels × 16 pixels; AVX2: 4 × 16, or 8 × 8 on images 8 wide):
//! for every input channel and tap, one unaligned load of the block's pixels from the
//! zero-padded image and a fused multiply-add per channel with the tap's weight broadcast. The
//! weights are packed eight output channels together (`[c_out / 8][c_in][9][8]`) so that a
//! block reads them contiguously. Cores without AVX2 and FMA keep im2col and the GEMM. (Written
//! first over fixed-size arrays left to the compiler's vectoriser, the same blocks ran slower
//! than im2col: it spilled the accumulators.)

use rayon::prelude::*;

use super::kernels::Kernels;

/// Output channels packed together in the weights.
const PACK: usize = 8;

/// The instructions a direct convolution runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Isa {
    Avx2,
    Avx512,
}

/// A 3 × 3 convolution at padding 1 and stride 1 or 2, without bias, its weights packed for
/// the direct kernel.
#[derive(Debug, Clone)]
pub(super) struct Conv3x3 {
    c_in: usize,
    c_out: usize,
    stride: usize,
    /// `[c_out / PACK][c_in][9][PACK]`.
    packed: Vec<f32>,
    isa: Isa,
}

impl Conv3x3 {
    /// The direct kernel for `weight` (`[c_out, c_in·9]`, taps row-major) at `stride` on this
    /// core under `kernels`, or `None` where it does not run: no AVX2 with FMA (or `kernels`
    /// allows none of the project's own), output channels not a multiple of eight, or a stride
    /// other than 1 and 2.
    pub(super) fn new(
        weight: &[f32],
        (c_in, c_out): (usize, usize),
        stride: usize,
        kernels: Kernels,
    ) -> Option<Self> {
        let isa = isa(kernels)?;
        if c_out % PACK != 0 || weight.len() != c_out * c_in * 9 || !(1..=2).contains(&stride) {
            return None;
        }
        let mut packed = vec![0.0; weight.len()];
        for (o, row) in weight.chunks_exact(c_in * 9).enumerate() {
            let (group, lane) = (o / PACK, o % PACK);
            for (t, w) in row.iter().enumerate() {
                // Tap t of input channel t / 9.
                packed[(group * c_in * 9 + t) * PACK + lane] = *w;
            }
        }
        Some(Conv3x3 {
            c_in,
            c_out,
            stride,
            packed,
            isa,
        })
    }

    /// The instructions it runs on, in words.
    pub(super) fn isa_name(&self) -> &'static str {
        match self.isa {
            Isa::Avx2 => "AVX2",
            Isa::Avx512 => "AVX-512",
        }
    }

    /// The output side of an input of side `(h, w)`, where the kernel runs on it: an output
    /// width that is a multiple of 8, and at stride 2 an even input side.
    pub(super) fn out_side(&self, (h, w): (usize, usize)) -> Option<(usize, usize)> {
        let out = match self.stride {
            1 => (h, w),
            _ if h % 2 == 0 && w % 2 == 0 => (h / 2, w / 2),
            _ => return None,
        };
        (out.1 % 8 == 0 && out.0 > 0).then_some(out)
    }

    /// `y = W ⋆ x` of one image `x` (`[c_in, h, w]`) into `y` (`[c_out, ho, wo]`), the output
    /// channels split between rayon's threads; `scratch` holds the padded image. Only where
    /// [`Conv3x3::out_side`] is `Some`.
    pub(super) fn forward(
        &self,
        x: &[f32],
        side: (usize, usize),
        scratch: &mut Vec<f32>,
        y: &mut [f32],
    ) {
        let out = self
            .out_side(side)
            .unwrap_or_else(|| panic!("no direct kernel for {side:?} at stride {}", self.stride));
        let layout = Layout::of(side, self.c_in, self.stride);
        layout.fill(x, side, scratch);
        let (buffer, m) = (&scratch[..], out.0 * out.1);
        let groups = self.c_out / PACK;
        // Groups of eight channels per task: at least two tasks per thread where there are
        // enough groups.
        let per_task = groups.div_ceil(2 * rayon::current_num_threads()).max(1);
        y[..self.c_out * m]
            .par_chunks_mut(per_task * PACK * m)
            .enumerate()
            .for_each(|(t, y)| {
                for (g, y) in y.chunks_exact_mut(PACK * m).enumerate() {
                    let group = t * per_task + g;
                    let weights =
                        &self.packed[group * self.c_in * 9 * PACK..][..self.c_in * 9 * PACK];
                    let image = Image {
                        buffer,
                        layout,
                        out,
                    };
                    self.isa.group(&image, weights, y);
                }
            });
    }
}

/// Where a block reads: the buffer's planes and rows, and each tap's offset in them.
#[derive(Debug, Clone, Copy)]
struct Layout {
    c_in: usize,
    stride: usize,
    /// Values from one input channel's plane to the next.
    plane: usize,
    /// Values from one output row's inputs to the next.
    row_step: usize,
    /// The offset of tap `dy·3 + dx` from output pixel (0, 0)'s.
    taps: [usize; 9],
    /// The padded row's length.
    padded_width: usize,
}

impl Layout {
    /// The buffer of an input of side `(h, w)` with `c_in` channels at `stride`.
    fn of((h, w): (usize, usize), c_in: usize, stride: usize) -> Layout {
        let (hp, wp) = (h + 2, w + 2);
        // At stride 2 a padded row holds its even columns, then its odd ones (wp is even).
        let tap = |dy: usize, dx: usize| match stride {
            1 => dy * wp + dx,
            _ => dy * wp + if dx == 1 { wp / 2 } else { dx / 2 },
        };
        assert!(stride == 1 || wp % 2 == 0, "stride {stride} of width {w}");
        Layout {
            c_in,
            stride,
            plane: hp * wp,
            row_step: stride * wp,
            taps: std::array::from_fn(|t| tap(t / 3, t % 3)),
            padded_width: wp,
        }
    }

    /// `x` (`[c_in, h, w]`) zero-padded into `buffer` as this layout reads it.
    fn fill(&self, x: &[f32], (h, w): (usize, usize), buffer: &mut Vec<f32>) {
        let wp = self.padded_width;
        buffer.clear();
        buffer.resize(self.c_in * self.plane, 0.0);
        for (plane, src) in buffer
            .chunks_exact_mut(self.plane)
            .zip(x.chunks_exact(h * w))
        {
            for (row, src) in plane.chunks_exact_mut(wp).skip(1).zip(src.chunks_exact(w)) {
                if self.stride == 2 {
                    // Padded column j = i + 1 of source column i: even j first, then odd.
                    let (even, odd) = row.split_at_mut(wp / 2);
                    for (i, v) in src.iter().enumerate() {
                        let j = i + 1;
                        if j % 2 == 0 {
                            even[j / 2] = *v
                        } else {
                            odd[j / 2] = *v
                        }
                    }
                } else {
                    row[1..=w].copy_from_slice(src);
                }
            }
        }
    }
}

/// One group's input: the buffer as its layout reads it, and the output side.
struct Image<'a> {
    buffer: &'a [f32],
    layout: Layout,
    out: (usize, usize),
}

impl Image<'_> {
    /// Where a block reads input channel `ci` for output row `oy` from pixel `x0` (its taps at
    /// the layout's offsets from there), and that channel's weights from output channel
    /// `first` of the group (its taps `PACK` apart).
    fn start(
        &self,
        (ci, oy, x0): (usize, usize, usize),
        weights: &[f32],
        first: usize,
    ) -> (*const f32, *const f32) {
        let l = &self.layout;
        (
            self.buffer
                .as_ptr()
                .wrapping_add(ci * l.plane + oy * l.row_step + x0),
            weights.as_ptr().wrapping_add(ci * 9 * PACK + first),
        )
    }
}

impl Isa {
    /// One group of eight output channels.
    fn group(self, image: &Image<'_>, weights: &[f32], y: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `self` was detected on this core by `isa`.
        unsafe {
            match self {
                Isa::Avx512 => group_avx512(image, weights, y),
                Isa::Avx2 => group_avx2(image, weights, y),
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        unreachable!(
            "{self:?} without x86-64: `isa` detects none ({}, {}, {})",
            image.buffer.len(),
            weights.len(),
            y.len()
        )
    }
}

/// The widest instructions the direct kernel may use on this core under `kernels`.
fn isa(kernels: Kernels) -> Option<Isa> {
    #[cfg(target_arch = "x86_64")]
    {
        let avx2 = std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma");
        if kernels.allows_avx512() && avx2 && std::is_x86_feature_detected!("avx512f") {
            return Some(Isa::Avx512);
        }
        if kernels.allows_own() && avx2 {
            return Some(Isa::Avx2);
        }
    }
    let _ = kernels;
    None
}

/// The sizes the raw reads of the kernels rely on: the weights hold `c_in·9·8` values, the
/// output `8·ho·wo`, the output width is a multiple of 8, and the last value a block reads
/// (the last channel's plane, the last output row, the farthest tap, the last output pixel)
/// lies inside the buffer.
fn check(image: &Image<'_>, weights: &[f32], y: &[f32]) {
    let (ho, wo) = image.out;
    let l = &image.layout;
    assert!(wo % 8 == 0 && ho > 0, "output side {ho} × {wo}");
    let last =
        (l.c_in - 1) * l.plane + (ho - 1) * l.row_step + l.taps.iter().max().unwrap() + wo - 1;
    assert!(
        last < image.buffer.len(),
        "buffer of {} for {last}",
        image.buffer.len()
    );
    assert!(weights.len() >= l.c_in * 9 * PACK, "weights");
    assert!(y.len() >= PACK * ho * wo, "output");
}

/// The eight output channels of one weight group (`weights`: `[c_in][9][PACK]`) into `y`
/// (`[8][ho][wo]`) on AVX-512: blocks of 8 channels × 16 pixels of a row (eight 512-bit
/// accumulators); outputs 8 wide (mod 16) on the AVX2 blocks.
///
/// # Safety
/// The core has AVX-512F, AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn group_avx512(image: &Image<'_>, weights: &[f32], y: &mut [f32]) {
    use std::arch::x86_64::*;
    let (ho, wo) = image.out;
    if wo % 16 != 0 {
        // SAFETY: the caller's contract.
        return unsafe { group_avx2(image, weights, y) };
    }
    check(image, weights, y);
    let l = image.layout;
    for oy in 0..ho {
        for x0 in (0..wo).step_by(16) {
            let mut acc = [_mm512_setzero_ps(); PACK];
            for ci in 0..l.c_in {
                // SAFETY: `check`: every value read lies in the buffer, every tap in `weights`.
                unsafe {
                    let (r, t) = image.start((ci, oy, x0), weights, 0);
                    for (tap, offset) in l.taps.iter().enumerate() {
                        let v = _mm512_loadu_ps(r.add(*offset));
                        for (c, acc) in acc.iter_mut().enumerate() {
                            let w = _mm512_set1_ps(*t.add(tap * PACK + c));
                            *acc = _mm512_fmadd_ps(w, v, *acc);
                        }
                    }
                }
            }
            for (c, acc) in acc.iter().enumerate() {
                let out = &mut y[(c * ho + oy) * wo + x0..][..16];
                // SAFETY: `out` holds 16 values.
                unsafe { _mm512_storeu_ps(out.as_mut_ptr(), *acc) };
            }
        }
    }
}

/// The eight output channels of one weight group into `y` on AVX2: blocks of 4 channels × 16
/// pixels of a row, or on outputs 8 wide (mod 16) 4 channels × 8 pixels of two rows (8 × 8 of
/// one row read each tap's eight weights for eight multiply-adds, and ran slower than im2col
/// at 8 × 8), eight 256-bit accumulators each.
///
/// # Safety
/// The core has AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn group_avx2(image: &Image<'_>, weights: &[f32], y: &mut [f32]) {
    check(image, weights, y);
    let (ho, wo) = image.out;
    let down = wo % 16 != 0;
    for first in [0, 4] {
        // SAFETY: the caller's contract and `check`.
        unsafe { blocks_avx2::<4, 2>(image, weights, y, (first, down)) };
    }
    if down && ho % 2 == 1 {
        // The last output row alone, as the one row of an image of its own: the rows above are
        // done.
        let last = Image {
            buffer: &image.buffer[(ho - 1) * image.layout.row_step..],
            layout: image.layout,
            out: (1, wo),
        };
        let mut row = vec![0.0; PACK * wo];
        for first in [0, 4] {
            // SAFETY: as above (`blocks_avx2` checks `last` in its turn).
            unsafe { blocks_avx2::<4, 1>(&last, weights, &mut row, (first, false)) };
        }
        for (c, r) in row.chunks_exact(wo).enumerate() {
            y[(c * ho + ho - 1) * wo..][..wo].copy_from_slice(r);
        }
    }
}

/// Output channels `first..first + CB` of a group in blocks of `CB` channels × `NV` vectors of
/// 8 pixels: side by side in a row, or with `down` one under the other in `NV` rows (the
/// output's last `ho % NV` rows are left to the caller).
///
/// # Safety
/// AVX2 and FMA; `first + CB ≤ 8`; the output width a multiple of `8·NV` (of 8 with `down`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn blocks_avx2<const CB: usize, const NV: usize>(
    image: &Image<'_>,
    weights: &[f32],
    y: &mut [f32],
    (first, down): (usize, bool),
) {
    use std::arch::x86_64::*;
    check(image, weights, y);
    assert!(first + CB <= PACK);
    let (ho, wo) = image.out;
    let l = image.layout;
    // Where vector j of a block starts, in the buffer and in an output plane.
    let (step_in, step_out) = if down { (l.row_step, wo) } else { (8, 8) };
    let (rows_per_block, pixels_per_block) = if down { (NV, 8) } else { (1, 8 * NV) };
    assert!(wo % pixels_per_block == 0, "width {wo}");
    for oy in (0..ho - ho % rows_per_block).step_by(rows_per_block) {
        for x0 in (0..wo).step_by(pixels_per_block) {
            let mut acc = [[_mm256_setzero_ps(); NV]; CB];
            for ci in 0..l.c_in {
                // SAFETY: `check`: every value read lies in the buffer, every tap in `weights`.
                unsafe {
                    let (r, t) = image.start((ci, oy, x0), weights, first);
                    for (tap, offset) in l.taps.iter().enumerate() {
                        let p = r.add(*offset);
                        let v: [__m256; NV] =
                            std::array::from_fn(|j| _mm256_loadu_ps(p.add(step_in * j)));
                        for (c, acc) in acc.iter_mut().enumerate() {
                            let w = _mm256_broadcast_ss(&*t.add(tap * PACK + c));
                            for (a, v) in acc.iter_mut().zip(&v) {
                                *a = _mm256_fmadd_ps(w, *v, *a);
                            }
                        }
                    }
                }
            }
            for (c, acc) in acc.iter().enumerate() {
                let out = &mut y[((first + c) * ho + oy) * wo + x0..];
                for (j, a) in acc.iter().enumerate() {
                    let out = &mut out[step_out * j..][..8];
                    // SAFETY: `out` holds 8 values.
                    unsafe { _mm256_storeu_ps(out.as_mut_ptr(), *a) };
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The convolution by its definition (padding 1), in f64.
    fn reference(
        weight: &[f32],
        x: &[f32],
        (c_in, c_out): (usize, usize),
        (h, w): (usize, usize),
        stride: usize,
    ) -> Vec<f32> {
        let (ho, wo) = (h.div_ceil(stride), w.div_ceil(stride));
        let mut y = vec![0.0; c_out * ho * wo];
        for o in 0..c_out {
            for oy in 0..ho {
                for ox in 0..wo {
                    let mut sum = 0f64;
                    for ci in 0..c_in {
                        for dy in 0..3 {
                            for dx in 0..3 {
                                // Padded coordinates; the image is at 1..=h, 1..=w.
                                let (iy, ix) = (oy * stride + dy, ox * stride + dx);
                                if iy < 1 || ix < 1 || iy > h || ix > w {
                                    continue;
                                }
                                let v = x[(ci * h + iy - 1) * w + ix - 1] as f64;
                                sum += weight[(o * c_in + ci) * 9 + dy * 3 + dx] as f64 * v;
                            }
                        }
                    }
                    y[(o * ho + oy) * wo + ox] = sum as f32;
                }
            }
        }
        y
    }

    /// Every kernel this core has computes the definition at strides 1 and 2, on the encoder's
    /// shapes and odd ones (three input channels, non-square images, 16 and 8 wide blocks, an
    /// odd number of rows); where the core has none, `new` says so.
    #[test]
    fn the_direct_kernels_compute_the_convolution() {
        let value =
            |i: usize, seed: usize| ((i * 2654435761 + seed * 97) % 1000) as f32 / 500.0 - 1.0;
        for kernels in [Kernels::Widest, Kernels::Avx2, Kernels::Portable] {
            for (c_in, c_out, side, stride) in [
                (3, 16, (64, 64), 1),
                (16, 16, (64, 64), 1),
                (16, 32, (64, 64), 2),
                (32, 32, (32, 32), 1),
                (32, 64, (32, 32), 2),
                (5, 24, (7, 24), 1),
                (64, 64, (16, 16), 1),
                (64, 128, (16, 16), 2),
                (128, 128, (8, 8), 1),
                (2, 8, (3, 40), 1),
                (3, 8, (10, 48), 2),
            ] {
                let weight: Vec<f32> = (0..c_out * c_in * 9).map(|i| value(i, 1)).collect();
                let x: Vec<f32> = (0..c_in * side.0 * side.1).map(|i| value(i, 2)).collect();
                let Some(conv) = Conv3x3::new(&weight, (c_in, c_out), stride, kernels) else {
                    assert!(kernels == Kernels::Portable || isa(kernels).is_none());
                    continue;
                };
                let out = conv.out_side(side).expect("a side the kernel runs");
                assert_eq!(out, (side.0.div_ceil(stride), side.1.div_ceil(stride)));
                let mut y = vec![f32::NAN; c_out * out.0 * out.1];
                conv.forward(&x, side, &mut Vec::new(), &mut y);
                let want = reference(&weight, &x, (c_in, c_out), side, stride);
                let worst = y
                    .iter()
                    .zip(&want)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0f32, f32::max);
                assert!(
                    worst < 1e-4 * (c_in as f32 * 9.0).sqrt(),
                    "{kernels} {c_in}→{c_out} {side:?} /{stride}: {worst}"
                );
            }
        }
        // Channels not a multiple of eight, output widths not a multiple of eight, odd sides at
        // stride 2 and strides above 2 are refused.
        assert!(Conv3x3::new(&[0.0; 12 * 9], (1, 12), 1, Kernels::Widest).is_none());
        assert!(Conv3x3::new(&[0.0; 8 * 9], (1, 8), 3, Kernels::Widest).is_none());
        if let Some(conv) = Conv3x3::new(&[0.0; 8 * 9], (1, 8), 1, Kernels::Widest) {
            assert_eq!(conv.out_side((4, 4)), None);
        }
        if let Some(conv) = Conv3x3::new(&[0.0; 8 * 9], (1, 8), 2, Kernels::Widest) {
            assert_eq!(conv.out_side((8, 8)), None);
            assert_eq!(conv.out_side((31, 32)), None);
            assert_eq!(conv.out_side((32, 32)), Some((16, 16)));
        }
    }
}
