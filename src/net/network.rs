//! The whole distribution network (encoder + dual-branch head), its input tensors, and the
//! grid's rotation projections that inference computes once per level.

use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};

use super::{BranchScores, DualHead, Encoder, EncoderConfig, HeadConfig, ResNetLayout};
use crate::encoding::RotationEncoding;
use crate::so3::{GridLevel, So3Error};

/// Rotations scored per chunk (bounds the activations' memory).
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
}

/// Encoder + dual-branch head.
#[derive(Module, Debug)]
pub struct Network {
    /// The image encoder.
    pub encoder: Encoder,
    /// The dual-branch head.
    pub head: DualHead,
}

impl NetworkConfig {
    /// Builds the network on `device`.
    pub fn init(&self, device: &Device) -> Network {
        Network {
            encoder: EncoderConfig::new(self.layout).init(device),
            head: HeadConfig::new(self.layout.feature_dim(), self.encoding.dim())
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
    let mut data = Vec::with_capacity(crops.len() * 3 * size * size);
    for rgb in crops {
        for c in 0..3 {
            data.extend(rgb.chunks_exact(3).map(|p| p[c] as f32 / 255.0));
        }
    }
    Tensor::from_data(TensorData::new(data, [crops.len(), 3, size, size]), device)
}

/// The grid's rotation projections, computed once: `[1, N, hidden]` in chunks.
pub struct ProjectedGrid {
    /// The level.
    pub grid: GridLevel,
    chunks: Vec<Tensor<3>>,
}

impl ProjectedGrid {
    /// Projects every cell centre of `level` through the head's rotation layer.
    pub fn new(
        network: &Network,
        config: &NetworkConfig,
        level: u8,
        device: &Device,
    ) -> Result<Self, So3Error> {
        let grid = GridLevel::new(level)?;
        let mats = grid.matrices_f32();
        let chunks = mats
            .chunks(CHUNK)
            .map(|c| {
                network
                    .head
                    .project_rotations(config.encoding.encode_tensor(c, device))
                    .unsqueeze::<3>()
            })
            .collect();
        Ok(Self { grid, chunks })
    }

    /// Combined log-weights of every cell for each image of a batch (row per image).
    pub fn log_weights(&self, network: &Network, images: Tensor<4>) -> Vec<Vec<f32>> {
        self.log_weights_of_features(network, network.encoder.forward(images))
    }

    /// As [`ProjectedGrid::log_weights`], from image features `[B, D]` already encoded.
    pub fn log_weights_of_features(&self, network: &Network, features: Tensor<2>) -> Vec<Vec<f32>> {
        self.branch_log_weights_of_features(network, features)
            .into_iter()
            .map(|(shape, feature)| shape.iter().zip(&feature).map(|(a, b)| a + b).collect())
            .collect()
    }

    /// Each branch's log-weights `(s_θ, s_φ)` of every cell, per image, from image features.
    pub fn branch_log_weights_of_features(
        &self,
        network: &Network,
        features: Tensor<2>,
    ) -> Vec<(Vec<f32>, Vec<f32>)> {
        let b = features.dims()[0];
        let n = self.grid.len();
        let mut out = vec![(Vec::with_capacity(n), Vec::with_capacity(n)); b];
        let read =
            |t: Tensor<2>| -> Vec<f32> { t.into_data().try_to_vec::<f32>().expect("float scores") };
        for chunk in &self.chunks {
            let scores = network
                .head
                .forward_projected(features.clone(), chunk.clone());
            let k = chunk.dims()[1];
            let (shape, feature) = (read(scores.shape), read(scores.feature));
            for (i, (s, f)) in out.iter_mut().enumerate() {
                s.extend_from_slice(&shape[i * k..(i + 1) * k]);
                f.extend_from_slice(&feature[i * k..(i + 1) * k]);
            }
        }
        out
    }
}
