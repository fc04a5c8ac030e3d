//! The ResNet encoder's training forward and backward by hand, for layouts of basic blocks without
//! a stem max-pool (`tiny`): the arithmetic of burn's autodiff through [`Encoder::forward`] on a
//! training device, on plain NCHW f32 batches, without the autodiff graph's per-op tensors.
//!
//! - A convolution (no bias, padding `k / 2`) is one GEMM per image over its im2col columns:
//!   `Y = W·cols(x)` with `W` as `[C_out, C_in·k·k]`; backward `dW = Σ_images dY·cols(x)ᵀ`, its
//!   right operand read from im2row's rows (`cols(x)ᵀ`, one row per output pixel), and
//!   `dx = col2im(Wᵀ·dY)`.
//! - BatchNorm uses the batch's statistics (biased variance, as burn) and updates the running
//!   ones by `momentum`; backward `dx = γ/σ · (dy − mean(dy) − x̂·mean(dy·x̂))`, `dγ = Σ dy·x̂`,
//!   `dβ = Σ dy`.
//! - A block is `relu(bn(conv(relu(bn(conv(x))))) + shortcut(x))`, the features the global
//!   average of the last block.
//!
//! Per-image weight gradients are summed in image order and channel statistics per channel in a
//! fixed order, so a step's result does not depend on the thread count. `tests/encoder_grad.rs`
//! holds it to burn's autodiff.

use burn::module::ParamId;
use burn::nn::BatchNorm;
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use super::dense::{Strided, gemm, read};
use super::encoder::{ConvBn, Encoder};
use super::kernels::Kernels;

/// Lanes the weight gradients of a convolution are summed in (images split in order).
const WEIGHT_LANES: usize = 4;

/// A batch of activations, `[images, channels, height, width]` row-major.
#[derive(Debug, Clone)]
struct Act {
    images: usize,
    channels: usize,
    side: (usize, usize),
    data: Vec<f32>,
}

impl Act {
    fn plane(&self) -> usize {
        self.side.0 * self.side.1
    }

    fn per_image(&self) -> usize {
        self.channels * self.plane()
    }
}

/// One conv + BatchNorm pair's weights and ids.
#[derive(Debug, Clone)]
pub(super) struct Unit {
    /// `[c_out, c_in·k·k]`.
    pub(super) weight: Vec<f32>,
    c_in: usize,
    pub(super) c_out: usize,
    k: usize,
    stride: usize,
    gamma: Vec<f32>,
    beta: Vec<f32>,
    epsilon: f64,
    ids: [ParamId; 3],
}

impl Unit {
    fn of(unit: &ConvBn) -> Option<Unit> {
        unit.parts()
            .1
            .training
            .is_enabled()
            .then(|| Unit::read(unit))
            .flatten()
    }

    /// The pair's weights, whatever its BatchNorm's training flag (the inference forward folds
    /// the running statistics in), or `None` for a convolution this path does not run (a
    /// bias, groups, dilation, a non-square or even kernel).
    pub(super) fn read(unit: &ConvBn) -> Option<Unit> {
        let (conv, bn) = unit.parts();
        let weight = conv.weight.val();
        let [c_out, c_in, k, k2] = weight.dims();
        let square = k == k2 && conv.stride[0] == conv.stride[1] && k % 2 == 1;
        let plain = conv.bias.is_none() && conv.groups == 1 && conv.dilation == [1, 1];
        if !square || !plain {
            return None;
        }
        Some(Unit {
            weight: read(weight),
            c_in,
            c_out,
            k,
            stride: conv.stride[0],
            gamma: read(bn.gamma.val()),
            beta: read(bn.beta.val()),
            epsilon: bn.epsilon,
            ids: [conv.weight.id, bn.gamma.id, bn.beta.id],
        })
    }

    /// The kernel's side.
    pub(super) fn k(&self) -> usize {
        self.k
    }

    /// The stride.
    pub(super) fn stride(&self) -> usize {
        self.stride
    }

    pub(super) fn columns(&self) -> usize {
        self.c_in * self.k * self.k
    }

    /// `γ / sqrt(var + ε)` and `β − mean · γ / sqrt(var + ε)` per output channel: the
    /// BatchNorm's inference affine map for its running `mean` and `variance`.
    pub(super) fn inference_affine(&self, mean: &[f32], variance: &[f32]) -> (Vec<f32>, Vec<f32>) {
        (0..self.c_out)
            .map(|c| {
                let scale = self.gamma[c] / (variance[c] as f64 + self.epsilon).sqrt() as f32;
                (scale, self.beta[c] - mean[c] * scale)
            })
            .unzip()
    }

    pub(super) fn out_side(&self, (h, w): (usize, usize)) -> (usize, usize) {
        let pad = self.k / 2;
        (
            (h + 2 * pad - self.k) / self.stride + 1,
            (w + 2 * pad - self.k) / self.stride + 1,
        )
    }
}

/// For one row of outputs of a column at horizontal offset `dx`: the first and one past the
/// last output `ox` whose input `ox·stride + dx − pad` lies inside a row of `w`.
fn inside(unit: &Unit, w: usize, wo: usize, dx: usize) -> (usize, usize) {
    let (s, pad) = (unit.stride, unit.k / 2);
    let lo = pad.saturating_sub(dx).div_ceil(s);
    // ox·s + dx − pad < w  ⇔  ox < (w + pad − dx) / s, rounded up.
    let hi = (w + pad).saturating_sub(dx).div_ceil(s).min(wo);
    (lo.min(hi), hi)
}

/// Visits each im2col row `r` (channel, dy, dx) and output row `oy` whose input row lies inside
/// the image and has at least one valid output: `visit(r, oy, input_row_start, (lo, hi))` with the valid outputs `lo..hi`, whose
/// inputs are `input_row_start + ox·stride + dx − pad`.
fn for_each_tap(
    unit: &Unit,
    (h, w): (usize, usize),
    mut visit: impl FnMut(usize, usize, usize, (usize, usize)),
) {
    let (ho, wo) = unit.out_side((h, w));
    let (k, pad) = (unit.k, unit.k / 2);
    for r in 0..unit.columns() {
        let (ci, dy, dx) = (r / (k * k), r / k % k, r % k);
        let range = inside(unit, w, wo, dx);
        if range.0 >= range.1 {
            continue;
        }
        for oy in 0..ho {
            let Some(iy) = (oy * unit.stride + dy)
                .checked_sub(pad)
                .filter(|&iy| iy < h)
            else {
                continue;
            };
            visit(r, oy, (ci * h + iy) * w, range);
        }
    }
}

/// The im2col columns of one image: `[c_in·k·k, ho·wo]`, zero where the window is outside.
/// Every value is written once, the zeros only where the window is outside (zeroing the whole
/// buffer first made the 64 px encoder 8–11 % slower: BENCHMARKS, "… and `im2col` without the fill").
fn im2col(unit: &Unit, x: &[f32], side: (usize, usize), cols: &mut [f32]) {
    let m = unit.out_side(side).0 * unit.out_side(side).1;
    im2col_rows(unit, x, side, 0, &mut cols[..unit.columns() * m]);
}

/// Rows `first..` of [`im2col`]'s columns, as many as `cols` holds (whole rows of `ho·wo`): so
/// that threads can fill one image's columns in parts.
pub(super) fn im2col_rows(
    unit: &Unit,
    x: &[f32],
    (h, w): (usize, usize),
    first: usize,
    cols: &mut [f32],
) {
    let (ho, wo) = unit.out_side((h, w));
    let m = ho * wo;
    let (s, k, pad) = (unit.stride, unit.k, unit.k / 2);
    for (r, row) in cols.chunks_exact_mut(m).enumerate() {
        let r = first + r;
        let (ci, dy, dx) = (r / (k * k), r / k % k, r % k);
        let (lo, hi) = inside(unit, w, wo, dx);
        for (oy, out) in row.chunks_exact_mut(wo).enumerate() {
            let iy = (oy * s + dy).checked_sub(pad).filter(|&iy| iy < h);
            let Some(iy) = iy.filter(|_| lo < hi) else {
                out.fill(0.0);
                continue;
            };
            out[..lo].fill(0.0);
            out[hi..].fill(0.0);
            // The input of output ox: (ci·h + iy)·w + ox·s + dx − pad (lo ≥ the first in range).
            let first = (ci * h + iy) * w + lo * s + dx - pad;
            match s {
                1 => out[lo..hi].copy_from_slice(&x[first..first + (hi - lo)]),
                _ => {
                    for (i, v) in out[lo..hi].iter_mut().enumerate() {
                        *v = x[first + i * s];
                    }
                }
            }
        }
    }
}

/// One image's channels-last copy: `[c, plane]` → `[plane, c]`, in tiles of 16 × 16 (both
/// sides of a tile in L1).
fn channels_last(x: &[f32], c: usize, plane: usize, out: &mut [f32]) {
    const TILE: usize = 16;
    let out = &mut out[..c * plane];
    let mut tile = [[0f32; TILE]; TILE];
    for c0 in (0..c).step_by(TILE) {
        let cs = TILE.min(c - c0);
        for p0 in (0..plane).step_by(TILE) {
            let ps = TILE.min(plane - p0);
            for (ch, t) in tile.iter_mut().enumerate().take(cs) {
                t[..ps].copy_from_slice(&x[(c0 + ch) * plane + p0..][..ps]);
            }
            for (i, o) in out[p0 * c..].chunks_exact_mut(c).take(ps).enumerate() {
                for (ch, v) in o[c0..c0 + cs].iter_mut().enumerate() {
                    *v = tile[ch][i];
                }
            }
        }
    }
}

/// The im2col columns of one image turned over, row per output pixel: `[ho·wo, k·k·c_in]`
/// with a row's values in tap-major order `(dy, dx, ci)`, from the image channels last
/// ([`channels_last`]): each tap one run of `c_in` values, zero where the window is outside.
/// The weight gradient's GEMM reads these rows as its right operand, `[pixels, taps]`
/// row-major, the layout its packing streams (`probe_conv_gemm`: the first stage's `dY·colsᵀ`
/// at 101–112 GFLOP/s on one Zen 4 core from these rows, 29–32 from im2col's columns).
fn im2row(unit: &Unit, x_last: &[f32], (h, w): (usize, usize), rows: &mut [f32]) {
    let (ho, wo) = unit.out_side((h, w));
    let (s, k, pad, c) = (unit.stride, unit.k, unit.k / 2, unit.c_in);
    let n = unit.columns();
    for (p, row) in rows[..ho * wo * n].chunks_exact_mut(n).enumerate() {
        let (oy, ox) = (p / wo, p % wo);
        for (t, run) in row.chunks_exact_mut(c).enumerate() {
            let (iy, ix) = (
                (oy * s + t / k).wrapping_sub(pad),
                (ox * s + t % k).wrapping_sub(pad),
            );
            match iy < h && ix < w {
                true => run.copy_from_slice(&x_last[(iy * w + ix) * c..][..c]),
                false => run.fill(0.0),
            }
        }
    }
}

/// `dW` in [`im2row`]'s tap-major column order `(dy, dx, ci)` → the weights' `(ci, dy, dx)`.
fn taps_to_channels(unit: &Unit, tap_major: &[f32]) -> Vec<f32> {
    let (n, kk, c) = (unit.columns(), unit.k * unit.k, unit.c_in);
    let mut out = vec![0.0; tap_major.len()];
    for (src, dst) in tap_major.chunks_exact(n).zip(out.chunks_exact_mut(n)) {
        for (i, v) in src.iter().enumerate() {
            let (t, ci) = (i / c, i % c);
            dst[ci * kk + t] = *v;
        }
    }
    out
}

/// The transpose of [`im2col`]: each column's gradient added back to its input.
fn col2im(unit: &Unit, cols: &[f32], side: (usize, usize), dx: &mut [f32]) {
    let (_, wo) = unit.out_side(side);
    let m = unit.out_side(side).0 * wo;
    let (s, k, pad) = (unit.stride, unit.k, unit.k / 2);
    for_each_tap(unit, side, |r, oy, start, (lo, hi)| {
        let row = &cols[r * m + oy * wo..][lo..hi];
        let first = start + lo * s + r % k - pad;
        // Slices, not indices: the adds vectorise (stride 1) and lose their bounds checks.
        match s {
            1 => {
                for (d, v) in dx[first..first + row.len()].iter_mut().zip(row) {
                    *d += v;
                }
            }
            _ => {
                let span = &mut dx[first..first + (row.len() - 1) * s + 1];
                for (d, v) in span.chunks_mut(s).zip(row) {
                    d[0] += v;
                }
            }
        }
    });
}

/// A BatchNorm's batch: the normalised input and `1/σ` per channel, and the batch's mean and
/// (biased) variance.
#[derive(Debug)]
struct NormPass {
    xhat: Vec<f32>,
    inv_std: Vec<f32>,
    mean: Vec<f32>,
    variance: Vec<f32>,
}

/// `(Σ a, Σ a·b)` of one plane, in 16 lanes (vectorised), added in a fixed order.
fn sum_and_dot(a: &[f32], b: &[f32]) -> (f64, f64) {
    let (mut s, mut t) = ([0f32; 16], [0f32; 16]);
    let (ac, bc) = (a.chunks_exact(16), b.chunks_exact(16));
    let (ar, br) = (ac.remainder(), bc.remainder());
    for (x, y) in ac.zip(bc) {
        for i in 0..16 {
            s[i] += x[i];
            t[i] += x[i] * y[i];
        }
    }
    let mut sums = (0f64, 0f64);
    for i in 0..16 {
        sums.0 += s[i] as f64;
        sums.1 += t[i] as f64;
    }
    for (x, y) in ar.iter().zip(br) {
        sums.0 += *x as f64;
        sums.1 += (*x * *y) as f64;
    }
    sums
}

/// Per channel, `(Σ a, Σ a·b)` over the batch, images in order.
fn channel_sums(act: &Act, other: &[f32]) -> Vec<(f64, f64)> {
    let plane = act.plane();
    (0..act.channels)
        .into_par_iter()
        .map(|c| {
            let mut sums = (0.0, 0.0);
            for image in 0..act.images {
                let at = (image * act.channels + c) * plane;
                let (s, t) = sum_and_dot(&act.data[at..at + plane], &other[at..at + plane]);
                sums.0 += s;
                sums.1 += t;
            }
            sums
        })
        .collect()
}

impl Unit {
    /// `bn(conv(x))` with the batch's statistics.
    fn forward(&self, kernels: Kernels, x: &Act) -> (Act, NormPass) {
        let (ho, wo) = self.out_side(x.side);
        let (n, m) = (self.columns(), ho * wo);
        let mut y = vec![0.0; x.images * self.c_out * m];
        y.par_chunks_mut(self.c_out * m)
            .zip(x.data.par_chunks(x.per_image()))
            .for_each_init(
                || vec![0.0; n * m],
                |cols, (y, x_img)| {
                    im2col(self, x_img, x.side, cols);
                    let (w, c) = (Strided::rows(&self.weight, n), Strided::rows(cols, m));
                    gemm(kernels, [self.c_out, n, m], w, c, 0.0, y);
                },
            );
        let mut out = Act {
            images: x.images,
            channels: self.c_out,
            side: (ho, wo),
            data: y,
        };
        let count = (x.images * m) as f64;
        let sums = channel_sums(&out, &out.data);
        let mean: Vec<f32> = sums.iter().map(|s| (s.0 / count) as f32).collect();
        let variance: Vec<f32> = sums
            .iter()
            .map(|s| (s.1 / count - (s.0 / count).powi(2)).max(0.0) as f32)
            .collect();
        let inv_std: Vec<f32> = variance
            .iter()
            .map(|v| 1.0 / (*v as f64 + self.epsilon).sqrt() as f32)
            .collect();
        // One task per image (a task per channel plane was 2 048 tasks of 16 values at the last
        // stage).
        let mut xhat = vec![0.0; out.data.len()];
        let c = self.c_out;
        xhat.par_chunks_mut(c * m)
            .zip(out.data.par_chunks_mut(c * m))
            .for_each(|(xh_img, o_img)| {
                let planes = xh_img.chunks_mut(m).zip(o_img.chunks_mut(m));
                for (ch, (xh, o)) in planes.enumerate() {
                    let (mean, inv_std) = (mean[ch], inv_std[ch]);
                    let (gamma, beta) = (self.gamma[ch], self.beta[ch]);
                    for (xh, o) in xh.iter_mut().zip(o.iter_mut()) {
                        *xh = (*o - mean) * inv_std;
                        *o = gamma * *xh + beta;
                    }
                }
            });
        let norm = NormPass {
            xhat,
            inv_std,
            mean,
            variance,
        };
        (out, norm)
    }

    /// From the gradient at the BatchNorm's output: the weights' gradients `[dW, dγ, dβ]` and,
    /// when asked, the input's.
    fn backward(
        &self,
        kernels: Kernels,
        x: &Act,
        norm: &NormPass,
        d_out: &Act,
        want_dx: bool,
    ) -> ([Vec<f32>; 3], Option<Act>) {
        let m = d_out.plane();
        let count = (d_out.images * m) as f64;
        let sums = channel_sums(d_out, &norm.xhat);
        let d_beta: Vec<f32> = sums.iter().map(|s| s.0 as f32).collect();
        let d_gamma: Vec<f32> = sums.iter().map(|s| s.1 as f32).collect();
        let mut dy = vec![0.0; d_out.data.len()];
        let c = self.c_out;
        let per_channel: Vec<(f32, f32, f32)> = (0..c)
            .map(|ch| {
                let scale = self.gamma[ch] * norm.inv_std[ch];
                let (mean_d, mean_dx) = ((sums[ch].0 / count) as f32, (sums[ch].1 / count) as f32);
                (scale, mean_d, mean_dx)
            })
            .collect();
        dy.par_chunks_mut(c * m)
            .zip(d_out.data.par_chunks(c * m))
            .zip(norm.xhat.par_chunks(c * m))
            .for_each(|((dy_img, d_img), xh_img)| {
                let planes = dy_img
                    .chunks_mut(m)
                    .zip(d_img.chunks(m))
                    .zip(xh_img.chunks(m));
                for (ch, ((dy, d), xh)) in planes.enumerate() {
                    let (scale, mean_d, mean_dx) = per_channel[ch];
                    for ((dy, d), xh) in dy.iter_mut().zip(d).zip(xh) {
                        *dy = scale * (*d - mean_d - xh * mean_dx);
                    }
                }
            });
        let (d_weight, dx) = self.conv_backward(kernels, x, &dy, want_dx);
        ([d_weight, d_gamma, d_beta], dx)
    }

    /// The convolution's backward from `dy` (`[images, c_out, ho·wo]`).
    fn conv_backward(
        &self,
        kernels: Kernels,
        x: &Act,
        dy: &[f32],
        want_dx: bool,
    ) -> (Vec<f32>, Option<Act>) {
        let (ho, wo) = self.out_side(x.side);
        let (n, m) = (self.columns(), ho * wo);
        let mut dx = vec![0.0; if want_dx { x.data.len() } else { 0 }];
        // Images in fixed lanes, each summing its images' dW in order (beta 1): the sum does not
        // depend on the thread count.
        let per_lane = x.images.div_ceil(WEIGHT_LANES).max(1);
        let mut dx_lanes: Vec<&mut [f32]> = match want_dx {
            true => dx.chunks_mut(per_lane * x.per_image()).collect(),
            false => Vec::new(),
        };
        dx_lanes.resize_with(x.images.div_ceil(per_lane), || &mut []);
        let lanes: Vec<Vec<f32>> = dy
            .par_chunks(per_lane * self.c_out * m)
            .zip(x.data.par_chunks(per_lane * x.per_image()))
            .zip(dx_lanes.into_par_iter())
            .map(|((dy, x_lane), dx_lane)| {
                let (mut rows, mut d_cols) = (vec![0.0; n * m], vec![0.0; n * m]);
                let mut x_last = vec![0.0; x.per_image()];
                let mut dw = vec![0.0; self.c_out * n];
                let images = dy.chunks(self.c_out * m).zip(x_lane.chunks(x.per_image()));
                for (i, (dy, x_img)) in images.enumerate() {
                    channels_last(x_img, x.channels, x.plane(), &mut x_last);
                    im2row(self, &x_last, x.side, &mut rows);
                    let (d, r) = (Strided::rows(dy, m), Strided::rows(&rows, n));
                    gemm(kernels, [self.c_out, m, n], d, r, 1.0, &mut dw);
                    if want_dx {
                        let (wt, d) = (Strided::columns(&self.weight, n), Strided::rows(dy, m));
                        gemm(kernels, [n, self.c_out, m], wt, d, 0.0, &mut d_cols);
                        let dx_img = &mut dx_lane[i * x.per_image()..][..x.per_image()];
                        col2im(self, &d_cols, x.side, dx_img);
                    }
                }
                dw
            })
            .collect();
        let mut d_weight = vec![0.0; self.c_out * n];
        for dw in &lanes {
            d_weight.iter_mut().zip(dw).for_each(|(t, v)| *t += v);
        }
        let d_weight = taps_to_channels(self, &d_weight);
        let dx = want_dx.then_some(Act {
            images: x.images,
            channels: x.channels,
            side: x.side,
            data: dx,
        });
        (d_weight, dx)
    }
}

fn relu(act: &mut Act) {
    act.data.iter_mut().for_each(|v| *v = v.max(0.0));
}

/// `d ← d ⊙ [activation > 0]`, branch-free.
fn mask_by(d: &mut Act, activation: &Act) {
    for (d, a) in d.data.iter_mut().zip(&activation.data) {
        *d = if *a > 0.0 { *d } else { 0.0 };
    }
}

/// A residual block's units: the main path's two, then the shortcut's (if any), as indices into
/// [`TrainingEncoder::units`].
#[derive(Debug, Clone, Copy)]
struct BlockUnits {
    first: usize,
    second: usize,
    shortcut: Option<usize>,
}

/// A block's forward, kept for its backward.
#[derive(Debug)]
struct BlockPass {
    first: NormPass,
    /// `relu(bn(conv(x)))`: the second conv's input.
    hidden: Act,
    second: NormPass,
    shortcut: Option<NormPass>,
    /// The block's output (after its ReLU).
    out: Act,
}

/// The encoder's forward pass, kept for its backward.
#[derive(Debug)]
pub struct EncoderPass {
    images: Act,
    stem: NormPass,
    stem_out: Act,
    blocks: Vec<BlockPass>,
    /// `[images, feature_dim]`.
    features: Vec<f32>,
}

impl EncoderPass {
    /// The image features, `[images, feature_dim]` row-major.
    pub fn features(&self) -> &[f32] {
        &self.features
    }
}

/// The gradients of one step and the BatchNorm statistics of its batch, in
/// [`TrainingEncoder`]'s unit order.
#[derive(Debug)]
pub struct EncoderGrads {
    /// Per unit: `[dW, dγ, dβ]`.
    pub units: Vec<[Vec<f32>; 3]>,
    /// Per unit: the batch's mean and (biased) variance.
    batch_stats: Vec<(Vec<f32>, Vec<f32>)>,
}

/// The encoder's weights, read for one training step.
#[derive(Debug, Clone)]
pub struct TrainingEncoder {
    /// The stem's unit first, then each block's (main path, then shortcut).
    units: Vec<Unit>,
    blocks: Vec<BlockUnits>,
    kernels: Kernels,
    /// Side of the pooling grid ([`Encoder::pool_grid`]).
    pool_grid: usize,
}

impl TrainingEncoder {
    /// Reads `encoder`'s weights for GEMMs on `kernels`, or `None` when its layout is not one
    /// this path runs (a stem max-pool, bottleneck blocks, a frozen BatchNorm): burn's autodiff
    /// trains those.
    pub fn of(encoder: &Encoder, kernels: Kernels) -> Option<TrainingEncoder> {
        let (stem, blocks) = encoder.basic_units()?;
        let mut units = vec![Unit::of(stem)?];
        let mut indices = Vec::new();
        for (first, second, shortcut) in blocks {
            let at = units.len();
            units.push(Unit::of(first)?);
            units.push(Unit::of(second)?);
            if let Some(s) = shortcut {
                units.push(Unit::of(s)?);
            }
            indices.push(BlockUnits {
                first: at,
                second: at + 1,
                shortcut: shortcut.map(|_| at + 2),
            });
        }
        Some(TrainingEncoder {
            units,
            blocks: indices,
            kernels,
            pool_grid: encoder.pool_grid(),
        })
    }

    /// Each unit's conv weight, BatchNorm γ and β ids, in [`EncoderGrads::units`]' order.
    pub fn param_ids(&self) -> Vec<[ParamId; 3]> {
        self.units.iter().map(|u| u.ids).collect()
    }

    /// The forward pass over RGB8 crops of `size`² (values / 255, as [`super::images_tensor`]).
    pub fn forward(&self, crops: &[&[u8]], size: usize) -> EncoderPass {
        let images = Act {
            images: crops.len(),
            channels: 3,
            side: (size, size),
            data: super::network::images_nchw(crops, size),
        };
        let (mut stem_out, stem) = self.units[0].forward(self.kernels, &images);
        relu(&mut stem_out);
        let mut blocks: Vec<BlockPass> = Vec::with_capacity(self.blocks.len());
        for b in &self.blocks {
            let x = blocks.last().map_or(&stem_out, |p| &p.out);
            blocks.push(self.block_forward(b, x));
        }
        let last = blocks.last().map_or(&stem_out, |p| &p.out);
        let features = super::encoder::grid_pool_planes(&last.data, last.side, self.pool_grid);
        EncoderPass {
            images,
            stem,
            stem_out,
            blocks,
            features,
        }
    }

    fn block_forward(&self, b: &BlockUnits, x: &Act) -> BlockPass {
        let (mut hidden, first) = self.units[b.first].forward(self.kernels, x);
        relu(&mut hidden);
        let (mut out, second) = self.units[b.second].forward(self.kernels, &hidden);
        let shortcut = match b.shortcut {
            Some(s) => {
                let (s_out, norm) = self.units[s].forward(self.kernels, x);
                out.data
                    .iter_mut()
                    .zip(&s_out.data)
                    .for_each(|(o, s)| *o += s);
                Some(norm)
            }
            None => {
                out.data.iter_mut().zip(&x.data).for_each(|(o, s)| *o += s);
                None
            }
        };
        relu(&mut out);
        BlockPass {
            first,
            hidden,
            second,
            shortcut,
            out,
        }
    }

    /// The backward pass of `pass` for the loss's gradient with respect to the features.
    pub fn backward(&self, pass: &EncoderPass, d_features: &[f32]) -> EncoderGrads {
        let mut units: Vec<Option<[Vec<f32>; 3]>> = vec![None; self.units.len()];
        let last = pass.blocks.last().map_or(&pass.stem_out, |p| &p.out);
        let g = self.pool_grid;
        assert_eq!(
            d_features.len(),
            last.images * last.channels * g * g,
            "feature gradient"
        );
        let mut d = Act {
            images: last.images,
            channels: last.channels,
            side: last.side,
            data: vec![0f32; last.data.len()],
        };
        for (plane, cells) in d
            .data
            .chunks_exact_mut(last.plane())
            .zip(d_features.chunks_exact(g * g))
        {
            super::encoder::grid_unpool(cells, last.side, g, plane);
        }
        for (i, (b, p)) in self.blocks.iter().zip(&pass.blocks).enumerate().rev() {
            let x = match i {
                0 => &pass.stem_out,
                i => &pass.blocks[i - 1].out,
            };
            d = self.block_backward(b, p, x, d, &mut units);
        }
        mask_by(&mut d, &pass.stem_out);
        let (g, _) = self.units[0].backward(self.kernels, &pass.images, &pass.stem, &d, false);
        units[0] = Some(g);
        let norms = std::iter::once(&pass.stem).chain(
            pass.blocks
                .iter()
                .flat_map(|p| [&p.first, &p.second].into_iter().chain(p.shortcut.as_ref())),
        );
        EncoderGrads {
            units: units
                .into_iter()
                .map(|u| u.expect("every unit ran"))
                .collect(),
            batch_stats: norms
                .map(|n| (n.mean.clone(), n.variance.clone()))
                .collect(),
        }
    }

    fn block_backward(
        &self,
        b: &BlockUnits,
        p: &BlockPass,
        x: &Act,
        mut d: Act,
        units: &mut [Option<[Vec<f32>; 3]>],
    ) -> Act {
        let k = self.kernels;
        mask_by(&mut d, &p.out);
        let (g, d_hidden) = self.units[b.second].backward(k, &p.hidden, &p.second, &d, true);
        units[b.second] = Some(g);
        let mut d_hidden = d_hidden.expect("asked for");
        mask_by(&mut d_hidden, &p.hidden);
        let (g, dx) = self.units[b.first].backward(k, x, &p.first, &d_hidden, true);
        units[b.first] = Some(g);
        let mut dx = dx.expect("asked for");
        let d_shortcut = match (b.shortcut, &p.shortcut) {
            (Some(s), Some(norm)) => {
                let (g, ds) = self.units[s].backward(k, x, norm, &d, true);
                units[s] = Some(g);
                ds.expect("asked for")
            }
            _ => d,
        };
        dx.data
            .iter_mut()
            .zip(&d_shortcut.data)
            .for_each(|(t, v)| *t += v);
        dx
    }
}

impl EncoderGrads {
    /// Registers every gradient under its parameter's id in `grads` (on `device`'s plain side,
    /// where burn's optimisers read them) and folds the batch's statistics into `encoder`'s
    /// BatchNorm running statistics, as burn's training forward does.
    pub fn register(
        self,
        model: &TrainingEncoder,
        encoder: &Encoder,
        grads: &mut GradientsParams,
        device: &Device,
    ) {
        let inner = device.clone().inner();
        for (unit, [dw, dg, db]) in model.units.iter().zip(self.units) {
            let shape = [unit.c_out, unit.c_in, unit.k, unit.k];
            let t = |v: Vec<f32>| Tensor::<1>::from_data(TensorData::new(v, [unit.c_out]), &inner);
            grads.register::<4>(
                unit.ids[0],
                Tensor::from_data(TensorData::new(dw, shape), &inner),
            );
            grads.register::<1>(unit.ids[1], t(dg));
            grads.register::<1>(unit.ids[2], t(db));
        }
        let (stem, _, blocks) = encoder.parts();
        let bns = stem.into_iter().chain(blocks.iter().flat_map(|b| {
            let (layers, shortcut) = b.parts();
            layers.iter().chain(shortcut)
        }));
        for (unit, (mean, variance)) in bns.zip(self.batch_stats) {
            update_running(unit.parts().1, mean, variance, device);
        }
    }
}

/// `running ← (1 − momentum)·running + momentum·batch`, for the mean and the variance.
fn update_running(bn: &BatchNorm, mean: Vec<f32>, variance: Vec<f32>, device: &Device) {
    let n = mean.len();
    let fold = |running: Tensor<1>, batch: Vec<f32>| {
        let batch = Tensor::<1>::from_data(TensorData::new(batch, [n]), device);
        running
            .mul_scalar(1.0 - bn.momentum)
            .add(batch.mul_scalar(bn.momentum))
    };
    let mean = fold(bn.running_mean.value_sync().to_device(device), mean);
    let variance = fold(bn.running_var.value_sync().to_device(device), variance);
    bn.running_mean.update(mean.detach());
    bn.running_var.update(variance.detach());
}
