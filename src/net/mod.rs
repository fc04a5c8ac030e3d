//! The distribution network: a ResNet image encoder, the rotation encoding, the dual-branch
//! head, and the losses that train it.

pub mod amx;
pub mod bf16;
mod conv3x3;
pub mod conv_bn;
pub(crate) mod dense;
pub mod efficientnet;
pub mod encoder;
pub mod encoder_eval;
pub mod encoder_grad;
pub mod f16;
pub mod fused;
pub mod head;
pub mod head_grad;
pub mod i8;
pub mod kernels;
pub mod loss;
pub mod native;
pub mod network;
pub mod tiles;
mod weights;

pub use efficientnet::{EfficientNetLite0, PretrainedError};
pub use encoder::{Encoder, EncoderConfig, ResNetLayout};
pub use encoder_eval::{InferenceEncoder, UnitTime};
pub use encoder_grad::{EncoderGrads, EncoderPass, TrainingEncoder};
pub use fused::{FusedHead, ReducedHead};
pub use head::{BranchScores, DualHead, HeadConfig};
pub use head_grad::{HeadGrads, HeadPass, TrainingHead};
pub use kernels::Kernels;
pub use loss::{
    LossGrad, contrast_loss, contrast_loss_grad, gkl_loss, gkl_loss_grad, ipdf_loss,
    ipdf_loss_grad, l1_measure_loss, l1_measure_loss_grad,
};
pub use network::{
    NETWORK_LIMITS, Network, NetworkConfig, NetworkLimits, ProjectedGrid, check_range,
    images_tensor,
};
pub use tiles::{Branches, Precision, Rows};
