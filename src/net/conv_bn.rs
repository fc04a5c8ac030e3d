//! A convolution followed by BatchNorm: the unit of both encoders, the ResNets of
//! [`super::encoder`] and EfficientNet-Lite0 of [`super::efficientnet`].

use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, PaddingConfig2d};
use burn::tensor::{Device, Tensor};

/// A `k × k` convolution without bias, padded by `k / 2`, over `groups` groups of channels.
fn conv(c: [usize; 2], k: usize, stride: usize, groups: usize, device: &Device) -> Conv2d {
    let p = k / 2;
    Conv2dConfig::new(c, [k, k])
        .with_stride([stride, stride])
        .with_padding(PaddingConfig2d::Explicit(p, p, p, p))
        .with_groups(groups)
        .with_bias(false)
        .init(device)
}

/// A conv + BatchNorm pair.
#[derive(Module, Debug)]
pub struct ConvBn {
    pub(crate) conv: Conv2d,
    pub(crate) bn: BatchNorm,
}

impl ConvBn {
    pub(crate) fn new(c_in: usize, c_out: usize, k: usize, stride: usize, device: &Device) -> Self {
        ConvBn {
            conv: conv([c_in, c_out], k, stride, 1, device),
            bn: BatchNormConfig::new(c_out).init(device),
        }
    }

    /// A pair of EfficientNet ([`super::efficientnet`]): `groups` groups of channels (a depthwise
    /// convolution with one per channel), BatchNorm ε 1e-3 and momentum 0.01 as its weights
    /// were trained.
    pub(crate) fn grouped(
        c: [usize; 2],
        k: usize,
        stride: usize,
        groups: usize,
        device: &Device,
    ) -> Self {
        ConvBn {
            conv: conv(c, k, stride, groups, device),
            bn: BatchNormConfig::new(c[1])
                .with_epsilon(1e-3)
                .with_momentum(0.01)
                .init(device),
        }
    }

    pub(crate) fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        self.bn.forward(self.conv.forward(x))
    }

    /// The convolution and its BatchNorm (the hand-written training path reads them).
    pub(crate) fn parts(&self) -> (&Conv2d, &BatchNorm) {
        (&self.conv, &self.bn)
    }

    /// This pair's weights in `into`, a pair of the same kernel with at least as many channels
    /// in and out, so that its own output channels compute what they did: their weights from
    /// the old inputs copied, from the added inputs zero; the added output channels keep
    /// `into`'s fresh weights and BatchNorm (scale 1, shift 0, running mean 0 and variance 1).
    /// The added channels are read by nothing that was there, so the encoder's old features are
    /// unchanged, and the gradient reaches the zero weights through the added channels' own
    /// (non-zero) activations. `None` when `into` is smaller or of another kernel.
    pub(crate) fn embedded_in(self, into: ConvBn, device: &Device) -> Option<Self> {
        use super::dense::read;
        use burn::module::RunningState;
        use burn::tensor::TensorData;
        let [o0, i0, k0, k0b] = self.conv.weight.dims();
        let [o1, i1, k1, k1b] = into.conv.weight.dims();
        if o1 < o0 || i1 < i0 || (k0, k0b) != (k1, k1b) {
            return None;
        }
        let kk = k0 * k0b;
        let old = read(self.conv.weight.val());
        let mut weight = read(into.conv.weight.val());
        for o in 0..o0 {
            for i in 0..i1 {
                let to = &mut weight[(o * i1 + i) * kk..][..kk];
                if i < i0 {
                    to.copy_from_slice(&old[(o * i0 + i) * kk..][..kk]);
                } else {
                    to.fill(0.0);
                }
            }
        }
        let joined = |old: Tensor<1>, fresh: Tensor<1>| {
            let mut v = read(fresh);
            let old = read(old);
            v[..old.len()].copy_from_slice(&old);
            Tensor::<1>::from_data(TensorData::new(v, [o1]), device)
        };
        let bn = BatchNorm {
            gamma: Param::from_tensor(joined(self.bn.gamma.val(), into.bn.gamma.val())),
            beta: Param::from_tensor(joined(self.bn.beta.val(), into.bn.beta.val())),
            running_mean: RunningState::new(joined(
                self.bn.running_mean.value_sync(),
                into.bn.running_mean.value_sync(),
            )),
            running_var: RunningState::new(joined(
                self.bn.running_var.value_sync(),
                into.bn.running_var.value_sync(),
            )),
            ..self.bn
        };
        let conv = Conv2d {
            weight: Param::from_tensor(Tensor::<4>::from_data(
                TensorData::new(weight, [o1, i1, k0, k0b]),
                device,
            )),
            ..self.conv
        };
        Some(ConvBn { conv, bn })
    }

    pub(crate) fn sync_running_stats(&self) {
        let _ = self.bn.running_mean.value_sync();
        let _ = self.bn.running_var.value_sync();
    }
}
