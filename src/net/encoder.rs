//! Image encoders of the ResNet family (He et al. 2016): a configurable stack of basic or
//! bottleneck residual blocks with BatchNorm, average pooling over a grid of cells (one cell:
//! global average pooling), and a feature vector.
//!
//! Layouts: `tiny` (the CPU default: basic blocks [1, 1, 1, 1], widths 16…128, a 3×3 stem for
//! 64×64 crops), `tiny_deep` (the same with two blocks per stage: a trained `tiny` encoder
//! warm-starts it unchanged, [`Encoder::grown`]), `tiny_wide` (`tiny_deep` with half as many
//! channels again, 24…192, which a trained `tiny` or `tiny_deep` encoder warm-starts the same
//! way), `resnet18` (basic [2, 2, 2, 2], 64…512) and
//! `resnet50` (bottleneck [3, 4, 6, 3], 64…512 × 4 = 2048 features) with the 7×7/2 stem and
//! max-pool for 224×224 crops.

pub use super::conv_bn::ConvBn;
use super::efficientnet::{EfficientNetLite0, PretrainedError};
use burn::config::Config;
use burn::module::{Module, Param};

use burn::nn::PaddingConfig2d;
use burn::nn::pool::{AdaptiveAvgPool2d, AdaptiveAvgPool2dConfig, MaxPool2d, MaxPool2dConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

/// A ResNet layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum ResNetLayout {
    /// Basic blocks [1, 1, 1, 1], widths 16, 32, 64, 128, 3×3 stem (CPU default).
    Tiny,
    /// Basic blocks [2, 2, 2, 2], widths 16, 32, 64, 128, 3×3 stem: `tiny` with a second block
    /// per stage (a `tiny` network warm-starts it, the added blocks starting as identities).
    TinyDeep,
    /// Basic blocks [2, 2, 2, 2], widths 24, 48, 96, 192, 3×3 stem: `tiny_deep` with half as
    /// many channels again (a `tiny` or `tiny_deep` network warm-starts it, the added channels
    /// read by nothing at the start).
    TinyWide,
    /// ResNet-18: basic blocks [2, 2, 2, 2], widths 64 … 512.
    Resnet18,
    /// ResNet-50: bottleneck blocks [3, 4, 6, 3], widths 64 … 512, expansion 4.
    Resnet50,
    /// Not a ResNet: EfficientNet-Lite0 ([`super::efficientnet`]), 1280 features, started from
    /// ImageNet weights (the layout for realistic crops of real parts).
    EfficientnetLite0,
}

impl ResNetLayout {
    fn blocks(&self) -> [usize; 4] {
        match self {
            ResNetLayout::Tiny => [1, 1, 1, 1],
            ResNetLayout::TinyDeep | ResNetLayout::TinyWide => [2, 2, 2, 2],
            ResNetLayout::Resnet18 => [2, 2, 2, 2],
            ResNetLayout::Resnet50 => [3, 4, 6, 3],
            ResNetLayout::EfficientnetLite0 => [0; 4],
        }
    }

    fn base_width(&self) -> usize {
        match self {
            ResNetLayout::Tiny | ResNetLayout::TinyDeep => 16,
            ResNetLayout::TinyWide => 24,
            _ => 64,
        }
    }

    /// A 3×3 stride-1 stem without a max-pool (the small crops of the CPU layouts), else the
    /// 7×7/2 stem and a max-pool of ImageNet ResNets.
    fn small_stem(&self) -> bool {
        matches!(
            self,
            ResNetLayout::Tiny | ResNetLayout::TinyDeep | ResNetLayout::TinyWide
        )
    }

    /// Whether an encoder of layout `from` becomes one of this layout by adding blocks and
    /// channels only (the same stem and block kind, at least as many channels, at least as many
    /// blocks per stage): its weights then warm-start this layout ([`Encoder::grown`]).
    pub fn grows(&self, from: ResNetLayout) -> bool {
        !self.is_efficientnet()
            && !from.is_efficientnet()
            && self.small_stem() == from.small_stem()
            && self.base_width() >= from.base_width()
            && self.bottleneck() == from.bottleneck()
            && self
                .blocks()
                .iter()
                .zip(from.blocks())
                .all(|(a, b)| *a >= b)
    }

    fn bottleneck(&self) -> bool {
        matches!(self, ResNetLayout::Resnet50)
    }

    /// Whether this is EfficientNet-Lite0 rather than a ResNet.
    pub fn is_efficientnet(&self) -> bool {
        matches!(self, ResNetLayout::EfficientnetLite0)
    }

    /// Length of the feature vector.
    pub fn feature_dim(&self) -> usize {
        if self.is_efficientnet() {
            return super::efficientnet::FEATURES;
        }
        self.base_width() * 8 * if self.bottleneck() { 4 } else { 1 }
    }
}

/// Encoder configuration.
#[derive(Config, Debug)]
pub struct EncoderConfig {
    /// The layout.
    pub layout: ResNetLayout,
    /// Side of the grid the last feature map is averaged over: 1 is global average pooling;
    /// `g` keeps where in the crop each of `g × g` cells' features lie (`g²` times the features).
    #[config(default = 1)]
    pub pool_grid: usize,
}

impl EncoderConfig {
    /// Length of the feature vector: the layout's channels times the pooling grid's cells.
    pub fn feature_dim(&self) -> usize {
        self.layout.feature_dim() * self.pool_grid * self.pool_grid
    }
}

/// The rows (or columns) `[start, end)` of a side of `side` pixels that cell `i` of `g` averages:
/// burn's adaptive average pooling's bins (cells overlap where `g` does not divide `side`).
fn pool_bin(i: usize, g: usize, side: usize) -> std::ops::Range<usize> {
    let start = ((i as f32 * side as f32) / g as f32).floor() as usize;
    let end = (((i + 1) as f32 * side as f32) / g as f32).ceil() as usize;
    start..end.min(side)
}

/// Average pooling of one channel's `plane` (`side.0 × side.1`, row-major) over a `g × g` grid of
/// cells, written to `out` (`g²` values, row-major over the cells): the features' pooling.
fn grid_pool(plane: &[f32], side: (usize, usize), g: usize, out: &mut [f32]) {
    for (cell, o) in out.iter_mut().enumerate() {
        let (rows, cols) = (pool_bin(cell / g, g, side.0), pool_bin(cell % g, g, side.1));
        let n = (rows.len() * cols.len()) as f32;
        let sum: f32 = rows
            .flat_map(|y| plane[y * side.1 + cols.start..y * side.1 + cols.end].iter())
            .sum();
        *o = sum / n;
    }
}

/// [`grid_pool`] of every channel plane of `maps` (planes of `side`, one after another): the
/// features, `g²` a plane, in the planes' order.
pub(crate) fn grid_pool_planes(maps: &[f32], side: (usize, usize), g: usize) -> Vec<f32> {
    let plane = side.0 * side.1;
    let mut features = vec![0f32; maps.len() / plane * g * g];
    for (p, cells) in maps
        .chunks_exact(plane)
        .zip(features.chunks_exact_mut(g * g))
    {
        grid_pool(p, side, g, cells);
    }
    features
}

/// The backward of [`grid_pool`]: adds each cell's gradient `d_cells`, shared over its pixels,
/// to the plane's gradient `d_plane`.
pub(crate) fn grid_unpool(d_cells: &[f32], side: (usize, usize), g: usize, d_plane: &mut [f32]) {
    for (cell, &d) in d_cells.iter().enumerate() {
        let (rows, cols) = (pool_bin(cell / g, g, side.0), pool_bin(cell % g, g, side.1));
        let share = d / (rows.len() * cols.len()) as f32;
        for y in rows {
            d_plane[y * side.1 + cols.start..y * side.1 + cols.end]
                .iter_mut()
                .for_each(|v| *v += share);
        }
    }
}

/// A basic block's units: the first and second convolution and the projection shortcut.
pub(crate) type BasicUnits<'a> = (&'a ConvBn, &'a ConvBn, Option<&'a ConvBn>);

/// A residual block: basic (3×3, 3×3) or bottleneck (1×1, 3×3, 1×1), with a projection
/// shortcut when the shape changes.
#[derive(Module, Debug)]
pub struct Block {
    layers: Vec<ConvBn>,
    shortcut: Option<ConvBn>,
}

impl Block {
    fn new(c_in: usize, width: usize, stride: usize, bottleneck: bool, device: &Device) -> Self {
        let (layers, c_out) = if bottleneck {
            let out = width * 4;
            (
                vec![
                    ConvBn::new(c_in, width, 1, 1, device),
                    ConvBn::new(width, width, 3, stride, device),
                    ConvBn::new(width, out, 1, 1, device),
                ],
                out,
            )
        } else {
            (
                vec![
                    ConvBn::new(c_in, width, 3, stride, device),
                    ConvBn::new(width, width, 3, 1, device),
                ],
                width,
            )
        };
        let shortcut =
            (stride != 1 || c_in != c_out).then(|| ConvBn::new(c_in, c_out, 1, stride, device));
        Block { layers, shortcut }
    }

    /// This block (of as many channels in as out, stride 1, no projection) as one that starts
    /// as the identity on the non-negative activations between blocks: its last BatchNorm's
    /// scale and shift are zero, so `relu(0 + x) = x` (the zero-initialised residual of Goyal
    /// et al. 2017), while the scale's gradient `Σ dy·x̂` is not zero and lets it learn.
    fn into_identity(mut self, device: &Device) -> Self {
        if let Some(last) = self.layers.last_mut() {
            let [channels] = last.bn.gamma.dims();
            last.bn.gamma = Param::from_tensor(Tensor::zeros([channels], device));
            last.bn.beta = Param::from_tensor(Tensor::zeros([channels], device));
        }
        self
    }

    /// This block's weights in `into`, a block of the same kind and stride with at least as many
    /// channels ([`ConvBn::embedded_in`] for each unit); `None` when their units do not match.
    fn embedded_in(self, into: Block, device: &Device) -> Option<Self> {
        if self.layers.len() != into.layers.len()
            || self.shortcut.is_some() != into.shortcut.is_some()
        {
            return None;
        }
        let layers = self
            .layers
            .into_iter()
            .zip(into.layers)
            .map(|(old, new)| old.embedded_in(new, device))
            .collect::<Option<Vec<_>>>()?;
        let shortcut = match (self.shortcut, into.shortcut) {
            (Some(old), Some(new)) => Some(old.embedded_in(new, device)?),
            _ => None,
        };
        Some(Block { layers, shortcut })
    }

    /// The main path's conv + BatchNorm pairs and the projection shortcut.
    pub(crate) fn parts(&self) -> (&[ConvBn], Option<&ConvBn>) {
        (&self.layers, self.shortcut.as_ref())
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let identity = match &self.shortcut {
            Some(s) => s.forward(x.clone()),
            None => x.clone(),
        };
        let last = self.layers.len() - 1;
        let mut h = x;
        for (i, layer) in self.layers.iter().enumerate() {
            h = layer.forward(h);
            if i < last {
                h = relu(h);
            }
        }
        relu(h + identity)
    }
}

/// An image encoder: `[B, 3, H, W]` in `[0, 1]` → `[B, feature_dim]`. A ResNet (`stem`, its
/// max-pool, `blocks`), or EfficientNet-Lite0 (`efficientnet`, the ResNet's fields empty); then
/// the pooling. (Absent modules add nothing to a record: the bundles of ResNets read as before.)
#[derive(Module, Debug)]
pub struct Encoder {
    stem: Option<ConvBn>,
    stem_pool: Option<MaxPool2d>,
    blocks: Vec<Block>,
    efficientnet: Option<EfficientNetLite0>,
    pool: AdaptiveAvgPool2d,
}

impl EncoderConfig {
    /// Builds the encoder on `device`.
    pub fn init(&self, device: &Device) -> Encoder {
        let layout = self.layout;
        let pool = AdaptiveAvgPool2dConfig::new([self.pool_grid; 2]).init();
        if layout.is_efficientnet() {
            return Encoder {
                stem: None,
                stem_pool: None,
                blocks: Vec::new(),
                efficientnet: Some(EfficientNetLite0::new(device)),
                pool,
            };
        }
        let base = layout.base_width();
        let (stem, stem_pool) = if layout.small_stem() {
            (ConvBn::new(3, base, 3, 1, device), None)
        } else {
            (
                ConvBn::new(3, base, 7, 2, device),
                Some(
                    MaxPool2dConfig::new([3, 3])
                        .with_strides([2, 2])
                        .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                        .init(),
                ),
            )
        };
        let mut blocks = Vec::new();
        let mut c_in = base;
        for (stage, &n) in layout.blocks().iter().enumerate() {
            let width = base << stage;
            for i in 0..n {
                let stride = if i == 0 && stage > 0 { 2 } else { 1 };
                let block = Block::new(c_in, width, stride, layout.bottleneck(), device);
                c_in = if layout.bottleneck() {
                    width * 4
                } else {
                    width
                };
                blocks.push(block);
            }
        }
        Encoder {
            stem: Some(stem),
            stem_pool,
            blocks,
            efficientnet: None,
            pool,
        }
    }

    /// EfficientNet-Lite0 with the ImageNet weights of `path` (`scripts/fetch_pretrained.sh`),
    /// pooled as this configuration says; `None` for the other layouts (they start fresh).
    pub fn init_pretrained(
        &self,
        path: &std::path::Path,
        device: &Device,
    ) -> Option<Result<Encoder, PretrainedError>> {
        self.layout.is_efficientnet().then(|| {
            let mut encoder = self.init(device);
            encoder.efficientnet = match encoder.efficientnet.take() {
                Some(net) => Some(net.with_weights_of(path)?),
                None => None,
            };
            Ok(encoder)
        })
    }
}

impl Encoder {
    /// Folds the BatchNorm running statistics of the last training steps into their stored
    /// values. burn keeps each step's update pending until read with `value_sync`, and saving
    /// reads the stored value: call this before saving or evaluating a trained encoder.
    pub fn sync_running_stats(&self) {
        if let Some(net) = &self.efficientnet {
            net.sync_running_stats();
        }
        if let Some(stem) = &self.stem {
            stem.sync_running_stats();
        }
        for block in &self.blocks {
            block.layers.iter().for_each(ConvBn::sync_running_stats);
            if let Some(s) = &block.shortcut {
                s.sync_running_stats();
            }
        }
    }

    /// This encoder, of layout `from`, as one of layout `to` that computes the same features,
    /// followed by those of the channels `to` adds (which nothing reads yet, [`DualHead`]'s
    /// `with_image_features`): each stage's blocks with their weights embedded in `to`'s wider
    /// ones ([`ConvBn::embedded_in`]), then the blocks `to` adds there, each starting as the
    /// identity. The added weights are drawn as a fresh `to` encoder's (under the caller's seed).
    ///
    /// [`DualHead`]: super::DualHead
    /// `None` when `to` does not grow `from` ([`ResNetLayout::grows`]).
    pub fn grown(self, from: ResNetLayout, to: ResNetLayout, device: &Device) -> Option<Self> {
        if !to.grows(from) {
            return None;
        }
        let fresh = EncoderConfig::new(to)
            .with_pool_grid(self.pool_grid())
            .init(device);
        let mut source = self.blocks.into_iter();
        let mut target = fresh.blocks.into_iter();
        let mut blocks = Vec::new();
        for (&have, &want) in from.blocks().iter().zip(&to.blocks()) {
            for (i, block) in target.by_ref().take(want).enumerate() {
                blocks.push(if i < have {
                    source.next()?.embedded_in(block, device)?
                } else {
                    block.into_identity(device)
                });
            }
        }
        Some(Encoder {
            stem: Some(self.stem?.embedded_in(fresh.stem?, device)?),
            blocks,
            ..self
        })
    }

    /// Side of the grid of cells the last feature map is averaged over (1: global pooling).
    pub fn pool_grid(&self) -> usize {
        self.pool.output_size[0]
    }

    /// This encoder averaging over a `g × g` grid of cells instead: the same weights, `g²`
    /// times the features (the head's image projection takes them with
    /// [`super::DualHead::with_image_cells`]).
    pub fn with_pool_grid(self, g: usize) -> Self {
        Encoder {
            pool: AdaptiveAvgPool2dConfig::new([g; 2]).init(),
            ..self
        }
    }

    /// The ResNet's stem (`None` for EfficientNet), whether a max-pool follows it, and its
    /// residual blocks.
    pub(crate) fn parts(&self) -> (Option<&ConvBn>, bool, &[Block]) {
        (self.stem.as_ref(), self.stem_pool.is_some(), &self.blocks)
    }

    /// The stem and each block's units (first, second, projection shortcut) where the layout
    /// is one the hand-written passes run (a ResNet of basic blocks, no stem max-pool), else
    /// `None`.
    pub(crate) fn basic_units(&self) -> Option<(&ConvBn, Vec<BasicUnits<'_>>)> {
        let stem = self.stem.as_ref()?;
        if self.stem_pool.is_some() {
            return None;
        }
        let blocks = self.blocks.iter().map(|block| match block.parts() {
            ([first, second], shortcut) => Some((first, second, shortcut)),
            _ => None,
        });
        Some((stem, blocks.collect::<Option<Vec<_>>>()?))
    }

    /// `[B, 3, H, W]` → `[B, feature_dim]`.
    pub fn forward(&self, images: Tensor<4>) -> Tensor<2> {
        let h = match (&self.efficientnet, &self.stem) {
            (Some(net), _) => net.forward(images),
            (None, Some(stem)) => {
                let mut h = relu(stem.forward(images));
                if let Some(pool) = &self.stem_pool {
                    h = pool.forward(h);
                }
                for block in &self.blocks {
                    h = block.forward(h);
                }
                h
            }
            (None, None) => unreachable!("an encoder is built with a ResNet stem or EfficientNet"),
        };
        let [b, c, _, _] = h.dims();
        let cells = self.pool_grid() * self.pool_grid();
        self.pool.forward(h).reshape([b, c * cells])
    }
}
