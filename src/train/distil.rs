//! A narrower head distilled from a trained model (a serving-cost measure, not the paper's): the
//! run takes the teacher's encoder and freezes it, and its head learns the teacher's two branch
//! scores `s_θ`, `s_φ` with the same per-branch generalised KL (paper Eq. 6) that fits the experts'
//! measures, at the rotations the step samples. The teacher already read the experts' measures
//! off realistic crops; its scores are those measures as the network can see them, so the student
//! needs no expert targets and no encoder backward.

use std::path::Path;

use burn::module::Module;
use burn::tensor::Device;

use super::TrainError;
use super::config::TeacherWeights;
use crate::encoding::RotationEncoding;
use crate::net::{Encoder, FusedHead, InferenceEncoder, Kernels, Network};

/// The teacher of a run: its encoder (folded for inference) and its head.
pub struct Teacher {
    encoder: InferenceEncoder,
    head: FusedHead,
    encoding: RotationEncoding,
}

/// The teacher's network, loaded from its checked weights file.
fn teacher_network(teacher: &TeacherWeights, device: &Device) -> Result<Network, TrainError> {
    let fail = |message: String| TrainError::Checkpoint {
        path: teacher.path.clone(),
        message,
    };
    teacher.network.validate().map_err(fail)?;
    crate::bundle::load_weights(
        teacher.network.init(device),
        Path::new(&teacher.path),
        &teacher.file,
    )
    .map_err(|e| fail(format!("the teacher's weights: {e}")))
}

impl Teacher {
    /// Loads the teacher and returns it with its encoder as a trainable module (the student's
    /// frozen encoder). `network` is the student's: the encoders must be the same tensors.
    pub fn load(
        teacher: &TeacherWeights,
        network: &crate::net::NetworkConfig,
        kernels: Kernels,
        device: &Device,
    ) -> Result<(Teacher, Encoder), TrainError> {
        check_pair(teacher, network)?;
        let loaded = teacher_network(teacher, device)?;
        let valid = loaded.valid();
        let encoder = InferenceEncoder::of(&valid.encoder, kernels).ok_or_else(|| {
            TrainError::Data(format!(
                "{}: a {:?} encoder has no folded inference path to distil from",
                teacher.path, teacher.network.layout
            ))
        })?;
        Ok((
            Teacher {
                encoder,
                head: FusedHead::with_kernels(&valid.head, kernels),
                encoding: teacher.network.encoding,
            },
            loaded.encoder,
        ))
    }

    /// The features of `crops` (`size`² RGB8): the teacher's, which are the student's.
    pub fn features(&self, crops: &[&[u8]], size: usize) -> Vec<Vec<f32>> {
        self.encoder.features(crops, size)
    }

    /// The teacher's branch scores `(s_θ, s_φ)` of each image's rotations, concatenated in
    /// image order (`[B, K]` each): the student's targets.
    pub fn targets(
        &self,
        features: &[Vec<f32>],
        rotations: &[Vec<[f32; 9]>],
    ) -> (Vec<f32>, Vec<f32>) {
        let (mut shape, mut feature) = (Vec::new(), Vec::new());
        for (f, rots) in features.iter().zip(rotations) {
            let projected = self.head.project_rotations(&self.encoding.encode(rots));
            let (s, e) = self
                .head
                .branch_scores(&self.head.image_term(f), &projected);
            shape.extend(s);
            feature.extend(e);
        }
        (shape, feature)
    }
}

/// Refuses a student whose encoder is not the teacher's (layout, crop side, pooling grid) or
/// whose rotation encoding is not: the one check of `fit --teacher` and of [`Teacher::load`].
pub fn check_pair(
    teacher: &TeacherWeights,
    network: &crate::net::NetworkConfig,
) -> Result<(), TrainError> {
    let t = &teacher.network;
    // Pooling compared as grids: an absent grid is 1 × 1 (global pooling).
    let (tg, ng) = (t.pooling(), network.pooling());
    if (t.layout, t.image_size, tg, &t.encoding)
        != (network.layout, network.image_size, ng, &network.encoding)
    {
        return Err(TrainError::Data(format!(
            "{}: the teacher is a {:?} network at {} px pooled over {tg}×{tg}, the run a {:?} \
             network at {} px pooled over {ng}×{ng}; a distilled head keeps the teacher's encoder, \
             so give its layout, crop side, pooling grid and rotation encoding",
            teacher.path, t.layout, t.image_size, network.layout, network.image_size,
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::record::FileEntry;
    use crate::net::{NetworkConfig, ResNetLayout};

    fn teacher(network: NetworkConfig) -> TeacherWeights {
        TeacherWeights {
            path: "models/teacher/network.safetensors".into(),
            file: FileEntry {
                sha256: String::new(),
                bytes: 0,
            },
            network,
            trained_by: String::new(),
        }
    }

    /// A grid written as 1 is global pooling, as an absent one is; another grid is refused, the
    /// message naming both grids.
    #[test]
    fn pooling_grids_are_compared_as_grids() {
        let plain = NetworkConfig::new(ResNetLayout::Tiny, RotationEncoding::Cube);
        let one = NetworkConfig {
            pool_grid: Some(1),
            ..plain.clone()
        };
        assert!(check_pair(&teacher(one.clone()), &plain).is_ok());
        assert!(check_pair(&teacher(plain.clone()), &one).is_ok());
        let err = check_pair(&teacher(plain.clone()), &plain.pooled_over(3))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("models/teacher") && err.contains("1×1") && err.contains("3×3"),
            "{err}"
        );
    }
}
