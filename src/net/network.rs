//! The whole distribution network (encoder + dual-branch head), its input tensors, and the
//! grid's rotation projections that inference computes once per level.

use burn::config::Config;
use burn::module::Module;
use std::sync::Arc;

use burn::tensor::{Device, Tensor, TensorData};

use super::{
    BranchScores, Branches, DualHead, Encoder, EncoderConfig, FusedHead, HeadConfig, Precision,
    ResNetLayout, Rows,
};
use crate::encoding::RotationEncoding;
use crate::so3::{GridLevel, So3Error};

/// Rotations encoded per chunk (bounds the encodings' memory).
const CHUNK: usize = 16_384;

/// Shape of the distribution network (recorded in bundles).
#[derive(Config, Debug, PartialEq)]
pub struct NetworkConfig {
    /// Encoder layout.
    pub layout: ResNetLayout,
    /// Rotation encoding.
    pub encoding: RotationEncoding,
    /// Side of the input crops.
    #[config(default = 64)]
    pub image_size: u32,
    /// Head width.
    #[config(default = 256)]
    pub hidden: usize,
    /// Linear layers per branch.
    #[config(default = 4)]
    pub layers: usize,
    /// Side of the grid of cells the encoder's last feature map is averaged over
    /// ([`EncoderConfig::pool_grid`]); `None` (absent from a manifest: every bundle before it) is
    /// 1, global average pooling. Set with [`NetworkConfig::pooled_over`], read with
    /// [`NetworkConfig::pooling`].
    #[config(default = "None")]
    pub pool_grid: Option<usize>,
}

/// Encoder + dual-branch head.
#[derive(Module, Debug)]
pub struct Network {
    /// The image encoder.
    pub encoder: Encoder,
    /// The dual-branch head.
    pub head: DualHead,
}

/// Sane ranges of a network's shape, checked before anything is allocated
/// ([`NetworkConfig::validate`]): a manifest is user input to the server.
pub const NETWORK_LIMITS: NetworkLimits = NetworkLimits {
    image_size: 8..=1024,
    hidden: 1..=4096,
    layers: 1..=16,
    frequencies: 1..=16,
    pool_grid: 1..=8,
};

/// Ranges of [`NETWORK_LIMITS`].
pub struct NetworkLimits {
    /// Side of the input crops.
    pub image_size: std::ops::RangeInclusive<u32>,
    /// Head width.
    pub hidden: std::ops::RangeInclusive<usize>,
    /// Linear layers per branch.
    pub layers: std::ops::RangeInclusive<usize>,
    /// IPDF encoding frequencies.
    pub frequencies: std::ops::RangeInclusive<usize>,
    /// Side of the encoder's pooling grid.
    pub pool_grid: std::ops::RangeInclusive<usize>,
}

/// `Err("field: value is outside lo ..= hi")` unless `value` lies in `range`.
pub fn check_range<T: PartialOrd + std::fmt::Display>(
    field: &str,
    value: T,
    range: &std::ops::RangeInclusive<T>,
) -> Result<(), String> {
    if range.contains(&value) {
        Ok(())
    } else {
        Err(format!(
            "{field}: {value} is outside {} ..= {}",
            range.start(),
            range.end()
        ))
    }
}

impl NetworkConfig {
    /// Checks the shape against [`NETWORK_LIMITS`]; the error names the field (`network.…`).
    pub fn validate(&self) -> Result<(), String> {
        let l = &NETWORK_LIMITS;
        check_range("network.image_size", self.image_size, &l.image_size)?;
        check_range("network.hidden", self.hidden, &l.hidden)?;
        check_range("network.layers", self.layers, &l.layers)?;
        check_range("network.pool_grid", self.pooling(), &l.pool_grid)?;
        if let RotationEncoding::Ipdf { frequencies } = self.encoding {
            check_range("network.encoding.frequencies", frequencies, &l.frequencies)?;
        }
        Ok(())
    }

    /// This network pooling its encoder's last map over a `g × g` grid of cells (1: globally).
    pub fn pooled_over(self, g: usize) -> Self {
        NetworkConfig {
            pool_grid: (g != 1).then_some(g),
            ..self
        }
    }

    /// Side of the encoder's pooling grid (1: global average pooling).
    pub fn pooling(&self) -> usize {
        self.pool_grid.unwrap_or(1)
    }

    /// The encoder's configuration.
    pub fn encoder(&self) -> EncoderConfig {
        EncoderConfig::new(self.layout).with_pool_grid(self.pooling())
    }

    /// Builds the network on `device`.
    pub fn init(&self, device: &Device) -> Network {
        Network {
            encoder: self.encoder().init(device),
            head: HeadConfig::new(self.encoder().feature_dim(), self.encoding.dim())
                .with_hidden(self.hidden)
                .with_layers(self.layers)
                .init(device),
        }
    }
}

impl Network {
    /// Scores per image: `images` `[B, 3, S, S]` in `[0, 1]`, `rotations[b]` the K rotations of
    /// image `b` (row-major matrices).
    pub fn scores(
        &self,
        images: Tensor<4>,
        rotations: &[Vec<[f32; 9]>],
        encoding: &RotationEncoding,
    ) -> BranchScores {
        self.scores_of_features(self.encoder.forward(images), rotations, encoding)
    }

    /// As [`Network::scores`], from image features `[B, D]` already encoded.
    pub fn scores_of_features(
        &self,
        features: Tensor<2>,
        rotations: &[Vec<[f32; 9]>],
        encoding: &RotationEncoding,
    ) -> BranchScores {
        let device = features.device();
        let b = rotations.len();
        let k = rotations.first().map_or(0, |r| r.len());
        let flat: Vec<[f32; 9]> = rotations.iter().flatten().copied().collect();
        let enc = encoding
            .encode_tensor(&flat, &device)
            .reshape([b, k, encoding.dim()]);
        self.head.forward(features, enc)
    }
}

/// Images as `[B, 3, S, S]` in `[0, 1]` from RGB8 crops.
pub fn images_tensor(crops: &[&[u8]], size: usize, device: &Device) -> Tensor<4> {
    let data = images_nchw(crops, size);
    Tensor::from_data(TensorData::new(data, [crops.len(), 3, size, size]), device)
}

/// RGB8 crops of `size`² as the network's input values: `[crops, 3, size, size]` row-major,
/// each value / 255.
pub fn images_nchw(crops: &[&[u8]], size: usize) -> Vec<f32> {
    let mut data = Vec::with_capacity(crops.len() * 3 * size * size);
    for rgb in crops {
        for c in 0..3 {
            data.extend(rgb.chunks_exact(3).map(|p| p[c] as f32 / 255.0));
        }
    }
    data
}

/// The grid's rotation projections, computed once per level (`[N, hidden]`), scored by the fused
/// inference head ([`FusedHead`]).
pub struct ProjectedGrid {
    /// The level.
    pub grid: GridLevel,
    head: Arc<FusedHead>,
    projected: Vec<f32>,
}

impl ProjectedGrid {
    /// Projects every cell centre of `level` through `network`'s rotation layer.
    pub fn new(network: &Network, config: &NetworkConfig, level: u8) -> Result<Self, So3Error> {
        Self::with_head(
            Arc::new(FusedHead::new(&network.head)),
            &config.encoding,
            level,
        )
    }

    /// As [`ProjectedGrid::new`], sharing an already read head.
    pub fn with_head(
        head: Arc<FusedHead>,
        encoding: &RotationEncoding,
        level: u8,
    ) -> Result<Self, So3Error> {
        let grid = GridLevel::new(level)?;
        let mats = grid.matrices_f32();
        let mut projected = Vec::with_capacity(mats.len() * head.width());
        for c in mats.chunks(CHUNK) {
            projected.extend(head.project_rotations(&encoding.encode(c)));
        }
        Ok(Self {
            grid,
            head,
            projected,
        })
    }

    /// Combined log-weights `s_θ + s_φ` of every cell for each image of `features` `[B, D]`
    /// (row per image).
    pub fn log_weights_of_features(&self, features: Tensor<2>) -> Vec<Vec<f32>> {
        self.log_weights_in(Precision::F32, features)
    }

    /// [`ProjectedGrid::log_weights_of_features`] in `precision`.
    pub fn log_weights_in(&self, precision: Precision, features: Tensor<2>) -> Vec<Vec<f32>> {
        feature_rows(features)
            .iter()
            .map(|f| self.log_weights_of_row(precision, f))
            .collect()
    }

    /// [`ProjectedGrid::log_weights_of_row`] in chunks of `rows` cells, calling `between` before
    /// each: long levels stop at the next chunk when it errs (a caller that went away).
    pub fn log_weights_of_row_in_chunks<E>(
        &self,
        precision: Precision,
        features: &[f32],
        rows: usize,
        mut between: impl FnMut() -> Result<(), E>,
    ) -> Result<Vec<f32>, E> {
        let image_term = self.head.image_term(features);
        let width = self.head.width();
        let mut out = Vec::with_capacity(self.grid.len());
        for chunk in self.projected.chunks(rows.max(1) * width) {
            between()?;
            out.extend(
                self.head
                    .scores_in(precision, &image_term, Rows::Projected(chunk)),
            );
        }
        Ok(out)
    }

    /// `s_θ + s_φ` of every cell for one image's features (a plain row of `D` floats), in
    /// `precision`.
    pub fn log_weights_of_row(&self, precision: Precision, features: &[f32]) -> Vec<f32> {
        self.log_weights_of_row_by(precision, Branches::Both, features)
    }

    /// [`ProjectedGrid::log_weights_of_row`] by `branches`: `s_θ + s_φ`, or `s_θ` alone.
    pub fn log_weights_of_row_by(
        &self,
        precision: Precision,
        branches: Branches,
        features: &[f32],
    ) -> Vec<f32> {
        self.head.scores_of(
            precision,
            &self.head.image_term(features),
            Rows::Projected(&self.projected),
            branches,
        )
    }

    /// [`ProjectedGrid::log_weights_of_row_by`] of some `cells` of the level only (in their
    /// order): their projections gathered, so a search's refined level skips the encoding and
    /// the rotation layer of the rows it scores. Panics on a cell outside the level.
    pub fn log_weights_of_cells_by(
        &self,
        precision: Precision,
        branches: Branches,
        features: &[f32],
        cells: &[u64],
    ) -> Vec<f32> {
        let width = self.head.width();
        let mut rows = Vec::with_capacity(cells.len() * width);
        for &c in cells {
            let at = c as usize * width;
            rows.extend_from_slice(&self.projected[at..at + width]);
        }
        self.head.scores_of(
            precision,
            &self.head.image_term(features),
            Rows::Projected(&rows),
            branches,
        )
    }

    /// The rotation of the cell with the highest combined log-weight, per image, from image
    /// features `[B, D]` (the point estimate AR@30 scores).
    pub fn argmax_rotations(&self, features: Tensor<2>) -> Vec<nalgebra::Rotation3<f64>> {
        self.log_weights_of_features(features)
            .iter()
            .map(|w| {
                let best = w
                    .iter()
                    .enumerate()
                    .max_by(|a, b| a.1.total_cmp(b.1))
                    .map_or(0, |(i, _)| i as u64);
                self.grid.rotation(best)
            })
            .collect()
    }

    /// The argmax rotation of every crop (RGB8, `size`² each), encoded by `network` eight at a
    /// time on the convolution device: how the probes and the own-twin search score a set.
    pub fn argmax_of_crops(
        &self,
        network: &Network,
        crops: &[&[u8]],
        size: usize,
    ) -> Vec<nalgebra::Rotation3<f64>> {
        let device = crate::backend::device_for(crate::backend::Workload::Conv);
        crops
            .chunks(8)
            .flat_map(|batch| {
                let features = network.encoder.forward(images_tensor(batch, size, &device));
                self.argmax_rotations(features)
            })
            .collect()
    }

    /// Each branch's log-weights `(s_θ, s_φ)` of every cell, per image, from image features.
    pub fn branch_log_weights_of_features(&self, features: Tensor<2>) -> Vec<(Vec<f32>, Vec<f32>)> {
        feature_rows(features)
            .iter()
            .map(|f| {
                self.head
                    .branch_scores(&self.head.image_term(f), &self.projected)
            })
            .collect()
    }
}

/// The rows of image features `[B, D]`.
pub fn feature_rows(features: Tensor<2>) -> Vec<Vec<f32>> {
    let [_, d] = features.dims();
    features
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .expect("float features")
        .chunks(d.max(1))
        .map(<[f32]>::to_vec)
        .collect()
}
