//! The dual-branch head (paper Sec. 3.3 and supplementary; docs/DESIGN.md §2): the image feature and
//! the rotation's positional encoding are each projected to 256, summed, and passed through two
//! ReLU MLPs (4 linear layers, 256 wide) that give the log-weights `s_θ(I, R)` (shape branch,
//! learns the SDF expert's measure) and `s_φ(I, R)` (feature branch, the SurfEmb expert's).

use burn::config::Config;
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

/// Head configuration.
#[derive(Config, Debug)]
pub struct HeadConfig {
    /// Length of the image feature.
    pub image_dim: usize,
    /// Length of the rotation encoding (144 for the cube encoding).
    pub rotation_dim: usize,
    /// Width of every hidden layer.
    #[config(default = 256)]
    pub hidden: usize,
    /// Linear layers per branch (the last one outputs the log-weight).
    #[config(default = 4)]
    pub layers: usize,
}

/// One branch: `layers − 1` hidden ReLU layers and a linear output.
#[derive(Module, Debug)]
pub struct Branch {
    hidden: Vec<Linear>,
    output: Linear,
}

impl Branch {
    fn new(width: usize, layers: usize, device: &Device) -> Self {
        Branch {
            hidden: (0..layers.saturating_sub(1))
                .map(|_| LinearConfig::new(width, width).init(device))
                .collect(),
            output: LinearConfig::new(width, 1).init(device),
        }
    }

    /// `[n, width]` (already ReLU'd) → `[n]`.
    fn forward(&self, x: Tensor<2>) -> Tensor<1> {
        let mut h = x;
        for layer in &self.hidden {
            h = relu(layer.forward(h));
        }
        let n = h.dims()[0];
        self.output.forward(h).reshape([n])
    }
}

/// The dual-branch head.
#[derive(Module, Debug)]
pub struct DualHead {
    image_proj: Linear,
    rotation_proj: Linear,
    shape_branch: Branch,
    feature_branch: Branch,
}

/// Log-weights of both branches, `[B, K]` each.
#[derive(Debug, Clone)]
pub struct BranchScores {
    /// `s_θ`, the shape (SDF) branch.
    pub shape: Tensor<2>,
    /// `s_φ`, the feature (SurfEmb) branch.
    pub feature: Tensor<2>,
}

impl BranchScores {
    /// `s_θ + s_φ`: the unnormalised log-density of the product of the two measures.
    pub fn combined(&self) -> Tensor<2> {
        self.shape.clone() + self.feature.clone()
    }
}

impl HeadConfig {
    /// Builds the head on `device`.
    pub fn init(&self, device: &Device) -> DualHead {
        DualHead {
            image_proj: LinearConfig::new(self.image_dim, self.hidden).init(device),
            rotation_proj: LinearConfig::new(self.rotation_dim, self.hidden).init(device),
            shape_branch: Branch::new(self.hidden, self.layers, device),
            feature_branch: Branch::new(self.hidden, self.layers, device),
        }
    }
}

impl Branch {
    /// The hidden layers and the output layer (for [`super::fused::FusedHead`]).
    pub(crate) fn layers(&self) -> (&[Linear], &Linear) {
        (&self.hidden, &self.output)
    }

    fn with_output_bias(mut self, value: f32) -> Self {
        self.output.bias = self.output.bias.map(|b| {
            b.map(|t| {
                let is_tracked = t.is_require_grad();
                let t = t.zeros_like().add_scalar(value);
                if is_tracked { t.require_grad() } else { t }
            })
        });
        self
    }
}

impl Branch {
    /// The branch with its output layer (weight and bias) multiplied by `scale`.
    fn scaled(mut self, scale: f32) -> Self {
        self.output.weight = self.output.weight.map(|w| w.mul_scalar(scale));
        self.output.bias = self.output.bias.map(|b| b.map(|t| t.mul_scalar(scale)));
        self
    }

    /// The branch with a zero output weight: it answers its output bias for every input, and,
    /// left out of the loss, gets no gradient and stays so (a single-expert ablation).
    fn silenced(mut self) -> Self {
        let weight = self.output.weight.val();
        let is_tracked = weight.is_require_grad();
        let zero = weight.zeros_like();
        let zero = if is_tracked {
            zero.require_grad()
        } else {
            zero
        };
        self.output.weight = burn::module::Param::from_tensor(zero);
        self
    }
}

impl DualHead {
    /// The image and rotation projections and the shape and feature branches (for
    /// [`super::fused::FusedHead`]).
    pub(crate) fn parts(&self) -> (&Linear, &Linear, &Branch, &Branch) {
        (
            &self.image_proj,
            &self.rotation_proj,
            &self.shape_branch,
            &self.feature_branch,
        )
    }

    /// Silences the shape (`shape = true`) or the feature branch: the combined score is then the
    /// other branch's up to a constant, so the model's distribution is that branch's.
    pub fn with_silenced_branch(mut self, shape: bool) -> Self {
        if shape {
            self.shape_branch = self.shape_branch.silenced();
        } else {
            self.feature_branch = self.feature_branch.silenced();
        }
        self
    }

    /// Sets the output bias of each branch: the log-weight every rotation starts from. The
    /// Alignist trainer starts it at the log of the targets' mean, so that the first steps fit
    /// the rotations' relative weights instead of dragging every output down to the targets'
    /// scale (which, measured, left every ReLU of the branches dead and the output constant).
    pub fn with_output_biases(mut self, shape: f32, feature: f32) -> Self {
        self.shape_branch = self.shape_branch.with_output_bias(shape);
        self.feature_branch = self.feature_branch.with_output_bias(feature);
        self
    }

    /// Both branches' outputs multiplied by `scale` (their output weights and biases): the
    /// combined log-density `s_θ + s_φ` times `scale`, a temperature of `1 / scale`
    /// (`train::calibrate`).
    pub fn with_output_scale(self, scale: f32) -> Self {
        self.with_branch_output_scales(scale, scale)
    }

    /// The shape branch's output multiplied by `shape` and the feature branch's by `feature`: the
    /// log-density `shape·s_θ + feature·s_φ`, each expert at its own temperature
    /// (`train::calibrate::fit_temperature`).
    pub fn with_branch_output_scales(mut self, shape: f32, feature: f32) -> Self {
        self.shape_branch = self.shape_branch.scaled(shape);
        self.feature_branch = self.feature_branch.scaled(feature);
        self
    }

    /// The head of an encoder that pools over `cells` cells ([`super::Encoder::with_pool_grid`])
    /// where this one's pooled globally, computing the same scores: each feature's row of the
    /// image projection repeated for each of its cells (features are channel-major: channel `c`'s
    /// cells are `c·cells .. (c+1)·cells`) and divided by `cells`, since the global average is the
    /// mean of the cells' (exactly so when the cells tile the map). Training then weighs the
    /// cells apart.
    pub fn with_image_cells(mut self, cells: usize) -> Self {
        self.image_proj.weight = self.image_proj.weight.map(|w| {
            let is_tracked = w.is_require_grad();
            let [d, h] = w.dims();
            let w = w
                .reshape([d, 1, h])
                .expand([d, cells, h])
                .reshape([d * cells, h])
                .div_scalar(cells as f32)
                .detach();
            if is_tracked { w.require_grad() } else { w }
        });
        self
    }

    /// The head of an encoder with `features` features where this one's had fewer, the added
    /// ones last (a grown encoder's added channels: [`super::Encoder::grown`]), computing the
    /// same scores: zero rows appended to the image projection, which training then fills.
    /// Unchanged when `features` is not more than it reads.
    pub fn with_image_features(mut self, features: usize) -> Self {
        self.image_proj.weight = self.image_proj.weight.map(|w| {
            let is_tracked = w.is_require_grad();
            let [d, h] = w.dims();
            if features <= d {
                return w;
            }
            let zeros = Tensor::zeros([features - d, h], &w.device());
            let w = Tensor::cat(vec![w, zeros], 0).detach();
            if is_tracked { w.require_grad() } else { w }
        });
        self
    }

    /// The rotation half of the first layer, `W_R · enc(R) + b_R`: `[K, E] → [K, hidden]`. It
    /// depends only on the rotations, so inference precomputes it once per grid level.
    pub fn project_rotations(&self, encodings: Tensor<2>) -> Tensor<2> {
        self.rotation_proj.forward(encodings)
    }

    /// Scores from image features `[B, D]` and per-image projected rotations `[B, K, hidden]`
    /// (or `[1, K, hidden]`, shared by every image).
    pub fn forward_projected(
        &self,
        image_features: Tensor<2>,
        rotations: Tensor<3>,
    ) -> BranchScores {
        let [b, _] = image_features.dims();
        let [rb, k, h] = rotations.dims();
        let img = self.image_proj.forward(image_features).reshape([b, 1, h]);
        let rotations = if rb == b {
            rotations
        } else {
            rotations.expand([b, k, h])
        };
        let x = relu(img + rotations).reshape([b * k, h]);
        BranchScores {
            shape: self.shape_branch.forward(x.clone()).reshape([b, k]),
            feature: self.feature_branch.forward(x).reshape([b, k]),
        }
    }

    /// Scores from image features `[B, D]` and rotation encodings `[B, K, E]`.
    pub fn forward(&self, image_features: Tensor<2>, encodings: Tensor<3>) -> BranchScores {
        let [b, k, e] = encodings.dims();
        let projected = self.project_rotations(encodings.reshape([b * k, e]));
        let h = projected.dims()[1];
        self.forward_projected(image_features, projected.reshape([b, k, h]))
    }
}
