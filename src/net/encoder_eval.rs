//! The encoder's inference forward by hand, for serving: the layouts of [`super::encoder_grad`]
//! (basic blocks, no stem max-pool), each convolution with its BatchNorm's running statistics
//! folded in (`W' = W·γ/σ`, `b' = β − mean·γ/σ`, σ = `sqrt(var + ε)`), so a unit is one
//! convolution plus a bias, and the ReLU and the residual add ride on the same pass. A 3 × 3 unit
//! runs the direct kernel where the core has one (`net::conv3x3`: at batch 1 the shipped
//! encoder 4.0 ms against 6.4 on Zen 3, `examples/probe_inference_encoder.rs`), the others one
//! GEMM over their im2col columns.
//!
//! burn's forward on the conv backend runs every op as its own tensor pass; here both cores
//! share each image: the output channels (and im2col's rows) are split between them.
//! `tests/net.rs` holds its features to burn's within 1e-4, with the direct kernels and without.

use rayon::prelude::*;

use super::conv3x3::Conv3x3;
use super::dense::{Strided, gemm, read};
use super::encoder::{ConvBn, Encoder};
use super::encoder_grad::{Unit, im2col_rows};
use super::kernels::Kernels;

/// A convolution with its BatchNorm folded in.
#[derive(Debug, Clone)]
struct Folded {
    /// The weights scaled per output channel (`Unit::weight` holds `[c_out, c_in·k·k]`).
    unit: Unit,
    bias: Vec<f32>,
    /// The direct kernel, for a 3 × 3 convolution on a core that has one.
    direct: Option<Conv3x3>,
}

impl Folded {
    fn of(conv_bn: &ConvBn, kernels: Kernels) -> Option<Folded> {
        let mut unit = Unit::read(conv_bn)?;
        let bn = conv_bn.parts().1;
        let mean = read(bn.running_mean.value_sync());
        let variance = read(bn.running_var.value_sync());
        let (scale, bias) = unit.inference_affine(&mean, &variance);
        let columns = unit.columns();
        for (row, s) in unit.weight.chunks_exact_mut(columns).zip(&scale) {
            row.iter_mut().for_each(|w| *w *= s);
        }
        let direct = (unit.k() == 3)
            .then(|| {
                Conv3x3::new(
                    &unit.weight,
                    (columns / 9, unit.c_out),
                    unit.stride(),
                    kernels,
                )
            })
            .flatten();
        Some(Folded { unit, bias, direct })
    }

    /// `W'·cols(x) + b'` of one image (`[c_in, h, w]`) into `[c_out, ho, wo]`, with its side,
    /// then as `after` says; `cols` is scratch. A 3 × 3 unit runs the direct kernel where it has
    /// one for this side ([`Conv3x3`]), the others im2col and the GEMM.
    fn forward(
        &self,
        kernels: Kernels,
        (x, side): (&[f32], (usize, usize)),
        after: After<'_>,
        cols: &mut Vec<f32>,
    ) -> (Vec<f32>, (usize, usize)) {
        let unit = &self.unit;
        let out = unit.out_side(side);
        let (n, m) = (unit.columns(), out.0 * out.1);
        let mut y = vec![0.0; unit.c_out * m];
        let threads = rayon::current_num_threads();
        let direct = self
            .direct
            .as_ref()
            .filter(|d| d.out_side(side) == Some(out));
        let mut by_pixels = false;
        if let Some(direct) = direct {
            direct.forward(x, side, cols, &mut y);
        } else {
            cols.resize(n * m, 0.0);
            // Rows of columns per task: a few tasks per thread, whole rows.
            let tasks = 2 * threads;
            let rows = n.div_ceil(tasks).max(1);
            cols[..n * m]
                .par_chunks_mut(rows * m)
                .enumerate()
                .for_each(|(t, chunk)| im2col_rows(unit, x, side, t * rows, chunk));
            by_pixels = unit.c_out < NARROW_CHANNELS * threads && m >= MIN_PIXELS * threads;
            if by_pixels {
                self.gemm_by_pixels(kernels, &cols[..n * m], m, threads, &mut y);
            }
        }
        let cols = &cols[..];
        let channels = unit.c_out.div_ceil(threads).max(1);
        y.par_chunks_mut(channels * m)
            .enumerate()
            .for_each(|(t, y)| {
                let first = t * channels;
                let c = y.len() / m;
                if direct.is_none() && !by_pixels {
                    let w = Strided::rows(&unit.weight[first * n..(first + c) * n], n);
                    gemm(
                        kernels,
                        [c, n, m],
                        w,
                        Strided::rows(&cols[..n * m], m),
                        0.0,
                        y,
                    );
                }
                for (ch, plane) in y.chunks_exact_mut(m).enumerate() {
                    let b = self.bias[first + ch];
                    match after {
                        After::AddRelu(r) => {
                            let r = &r[(first + ch) * m..(first + ch + 1) * m];
                            for (v, r) in plane.iter_mut().zip(r) {
                                *v = (*v + b + r).max(0.0);
                            }
                        }
                        After::Relu => plane.iter_mut().for_each(|v| *v = (*v + b).max(0.0)),
                        After::Nothing => plane.iter_mut().for_each(|v| *v += b),
                    }
                }
            });
        (y, out)
    }

    /// `W'·cols` into `y` (`[c_out, m]`), each thread all the output channels of a span of the
    /// `m` pixels: a narrow layer (16 channels at 64 × 64) split by channels would give each
    /// thread a GEMM of a few rows, which uses each element of the wide `cols` it packs only as
    /// many times (batch 1 on AMD Zen 3: the encoder 7.4–7.6 ms that way, 6.2–6.6 ms this way).
    fn gemm_by_pixels(
        &self,
        kernels: Kernels,
        cols: &[f32],
        m: usize,
        threads: usize,
        y: &mut [f32],
    ) {
        let unit = &self.unit;
        let (c, n) = (unit.c_out, unit.columns());
        let span = m.div_ceil(threads);
        let parts: Vec<Vec<f32>> = (0..m.div_ceil(span))
            .into_par_iter()
            .map(|t| {
                let (first, last) = (t * span, ((t + 1) * span).min(m));
                let mut part = vec![0.0; c * (last - first)];
                let w = Strided::rows(&unit.weight, n);
                // Row step m, columns first..last of `cols`.
                let b = Strided::rows(&cols[first..], m);
                gemm(kernels, [c, n, last - first], w, b, 0.0, &mut part);
                part
            })
            .collect();
        for (t, part) in parts.iter().enumerate() {
            let first = t * span;
            let width = part.len() / c;
            for (row, out) in part.chunks_exact(width).zip(y.chunks_exact_mut(m)) {
                out[first..first + width].copy_from_slice(row);
            }
        }
    }
}

/// Below this many output channels a thread, a convolution's GEMM is split by pixels
/// ([`Folded::gemm_by_pixels`]).
const NARROW_CHANNELS: usize = 32;

/// The fewest pixels a thread for the split by pixels.
const MIN_PIXELS: usize = 256;

/// What follows a folded convolution in the same pass.
#[derive(Debug, Clone, Copy)]
enum After<'a> {
    /// The stem and a block's first unit.
    Relu,
    /// A projection shortcut.
    Nothing,
    /// A block's second unit: the shortcut's output (same shape) added, then the ReLU.
    AddRelu(&'a [f32]),
}

/// A residual block's folded units.
#[derive(Debug, Clone)]
struct FoldedBlock {
    first: Folded,
    second: Folded,
    shortcut: Option<Folded>,
}

/// The encoder for inference with every BatchNorm folded into its convolution.
#[derive(Debug, Clone)]
pub struct InferenceEncoder {
    stem: Folded,
    blocks: Vec<FoldedBlock>,
    kernels: Kernels,
    /// Side of the pooling grid ([`Encoder::pool_grid`]).
    pool_grid: usize,
}

impl InferenceEncoder {
    /// `encoder`'s weights and running statistics for GEMMs on `kernels`, or `None` for a
    /// layout this path does not run (a stem max-pool, bottleneck blocks): burn runs those.
    pub fn of(encoder: &Encoder, kernels: Kernels) -> Option<InferenceEncoder> {
        let (stem, blocks) = encoder.basic_units()?;
        let blocks = blocks
            .into_iter()
            .map(|(first, second, shortcut)| {
                Some(FoldedBlock {
                    first: Folded::of(first, kernels)?,
                    second: Folded::of(second, kernels)?,
                    shortcut: match shortcut {
                        Some(s) => Some(Folded::of(s, kernels)?),
                        None => None,
                    },
                })
            })
            .collect::<Option<Vec<_>>>()?;
        Some(InferenceEncoder {
            stem: Folded::of(stem, kernels)?,
            blocks,
            kernels,
            pool_grid: encoder.pool_grid(),
        })
    }

    /// The same encoder with every convolution on im2col and the GEMM: the ablation of the
    /// direct kernels of `net::conv3x3` (`examples/probe_inference_encoder.rs`, `tests/net.rs`).
    pub fn im2col_only(mut self) -> InferenceEncoder {
        let units = std::iter::once(&mut self.stem).chain(self.blocks.iter_mut().flat_map(|b| {
            [&mut b.first, &mut b.second]
                .into_iter()
                .chain(b.shortcut.as_mut())
        }));
        units.for_each(|u| u.direct = None);
        self
    }

    /// Which kernels the convolutions of a `size`² crop's forward run on, in words.
    pub fn kernel_paths(&self, size: usize) -> String {
        let (mut side, mut direct, mut isa, mut total) = ((size, size), 0, None, 0);
        let mut visit = |unit: &Folded, side: (usize, usize)| {
            let out = unit.unit.out_side(side);
            total += 1;
            if let Some(d) = unit
                .direct
                .as_ref()
                .filter(|d| d.out_side(side) == Some(out))
            {
                direct += 1;
                isa = Some(d.isa_name());
            }
            out
        };
        side = visit(&self.stem, side);
        for block in &self.blocks {
            let hidden = visit(&block.first, side);
            if let Some(s) = &block.shortcut {
                visit(s, side);
            }
            side = visit(&block.second, hidden);
        }
        match isa {
            Some(isa) => format!(
                "{direct} of {total} convolutions direct 3×3 ({isa}), the others im2col + GEMM"
            ),
            None => format!("{total} convolutions im2col + GEMM"),
        }
    }

    /// Whether any convolution runs the direct kernel.
    pub fn has_direct(&self) -> bool {
        std::iter::once(&self.stem)
            .chain(self.blocks.iter().flat_map(|b| [&b.first, &b.second]))
            .any(|u| u.direct.is_some())
    }

    /// The features of RGB8 crops of `size`² (values / 255, as burn's forward reads them), a
    /// row per crop.
    pub fn features(&self, crops: &[&[u8]], size: usize) -> Vec<Vec<f32>> {
        crops
            .par_iter()
            .map(|crop| self.image_features(crop, size))
            .collect()
    }

    fn image_features(&self, crop: &[u8], size: usize) -> Vec<f32> {
        self.image_features_timed(crop, size, &mut |_, _| {})
    }

    /// Each convolution of one crop's forward, in order, with its milliseconds: its name
    /// (`stem`, `block B.1`, `block B.2`, `block B shortcut`), its shape and its multiply-adds
    /// (a profile for `examples/probe_inference_encoder.rs`).
    pub fn unit_times(&self, crop: &[u8], size: usize) -> Vec<UnitTime> {
        let mut units = Vec::new();
        self.image_features_timed(crop, size, &mut |name, (unit, side, ms)| {
            let out = unit.unit.out_side(side);
            units.push(UnitTime {
                name,
                shape: format!(
                    "{}→{} k{} /{} at {}×{}",
                    unit.unit.columns() / (unit.unit.k() * unit.unit.k()),
                    unit.unit.c_out,
                    unit.unit.k(),
                    unit.unit.stride(),
                    out.0,
                    out.1
                ),
                multiply_adds: unit.unit.c_out * unit.unit.columns() * out.0 * out.1,
                ms,
            });
        });
        units
    }

    /// The forward of one crop, telling `took` each convolution's name, unit, input side and
    /// milliseconds.
    fn image_features_timed(&self, crop: &[u8], size: usize, took: &mut UnitTook<'_>) -> Vec<f32> {
        let k = self.kernels;
        let mut cols = Vec::new();
        let mut timed = |name: &dyn Fn() -> String,
                         unit: &Folded,
                         input: (&[f32], (usize, usize)),
                         after: After<'_>,
                         cols: &mut Vec<f32>| {
            let started = std::time::Instant::now();
            let out = unit.forward(k, input, after, cols);
            took(
                name(),
                (unit, input.1, started.elapsed().as_secs_f64() * 1e3),
            );
            out
        };
        let image = super::network::images_nchw(&[crop], size);
        let (mut x, mut side) = timed(
            &|| "stem".into(),
            &self.stem,
            (&image, (size, size)),
            After::Relu,
            &mut cols,
        );
        for (b, block) in self.blocks.iter().enumerate() {
            let hidden = timed(
                &|| format!("block {b}.1"),
                &block.first,
                (&x, side),
                After::Relu,
                &mut cols,
            );
            let shortcut = block.shortcut.as_ref().map(|s| {
                timed(
                    &|| format!("block {b} shortcut"),
                    s,
                    (&x, side),
                    After::Nothing,
                    &mut cols,
                )
                .0
            });
            let residual = shortcut.as_deref().unwrap_or(&x);
            (x, side) = timed(
                &|| format!("block {b}.2"),
                &block.second,
                (&hidden.0, hidden.1),
                After::AddRelu(residual),
                &mut cols,
            );
        }
        super::encoder::grid_pool_planes(&x, side, self.pool_grid)
    }
}

/// What [`InferenceEncoder::unit_times`] is told of each convolution: its name, the unit, its
/// input side and its milliseconds.
type UnitTook<'a> = dyn FnMut(String, (&Folded, (usize, usize), f64)) + 'a;

/// One convolution's time in [`InferenceEncoder::unit_times`].
#[derive(Debug, Clone)]
pub struct UnitTime {
    /// `stem`, `block B.1`, `block B.2` or `block B shortcut`.
    pub name: String,
    /// Input → output channels, kernel side, stride and output side.
    pub shape: String,
    /// Its multiply-adds.
    pub multiply_adds: usize,
    /// Milliseconds.
    pub ms: f64,
}
