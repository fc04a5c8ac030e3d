//! The dual-branch head's weights as plain row-major f32 layers ([`Dense`]), read once from the
//! burn [`DualHead`]: what every inference path packs or reads ([`super::FusedHead`], the
//! native kernels of [`super::native`]).

use super::DualHead;
use super::dense::Dense;
use super::head::Branch;
use super::tiles::columns_to_i8;

/// One branch: hidden ReLU layers, then the `width → 1` output as a dot product.
#[derive(Debug, Clone)]
pub(super) struct BranchWeights {
    pub(super) hidden: Vec<Dense>,
    pub(super) output: Vec<f32>,
    pub(super) output_bias: f32,
}

impl BranchWeights {
    fn of(branch: &Branch) -> BranchWeights {
        let (hidden, output) = branch.layers();
        let output = Dense::of(output);
        BranchWeights {
            hidden: hidden.iter().map(Dense::of).collect(),
            output: output.weight,
            output_bias: output.bias[0],
        }
    }
}

/// A branch as the native kernels take it: hidden layers, padded output weights, output bias.
pub(super) type SquareBranch<'a> = (&'a [Dense], Vec<f32>, f32);

/// The head's weights: the image and rotation halves of the first layer and both branches
/// (`[shape, feature]`).
#[derive(Debug, Clone)]
pub(super) struct HeadWeights {
    pub(super) width: usize,
    pub(super) image: Dense,
    pub(super) rotation: Dense,
    pub(super) branches: [BranchWeights; 2],
}

impl HeadWeights {
    /// Reads `head`'s weights.
    pub(super) fn of(head: &DualHead) -> HeadWeights {
        let (image, rotation, shape, feature) = head.parts();
        let rotation = Dense::of(rotation);
        HeadWeights {
            width: rotation.outputs,
            image: Dense::of(image),
            rotation,
            branches: [BranchWeights::of(shape), BranchWeights::of(feature)],
        }
    }

    /// These weights with the branches' hidden layers and the rotation layer made by `layer`
    /// from their own (the image half of the first layer stays f32, as in the native kernels).
    fn with_layers(&self, layer: impl Fn(&Dense) -> Dense) -> HeadWeights {
        let branch = |b: &BranchWeights| BranchWeights {
            hidden: b.hidden.iter().map(&layer).collect(),
            ..b.clone()
        };
        HeadWeights {
            rotation: layer(&self.rotation),
            branches: [branch(&self.branches[0]), branch(&self.branches[1])],
            ..self.clone()
        }
    }

    /// These weights with the branches' and the rotation layer's weights rounded by `round`
    /// (to bfloat16 or f16).
    pub(super) fn rounded_by(&self, round: fn(f32) -> f32) -> HeadWeights {
        self.with_layers(|d| Dense {
            weight: d.weight.iter().copied().map(round).collect(),
            ..d.clone()
        })
    }

    /// These weights as the 8-bit head reads them: the branches' and the rotation layer's
    /// weights on their columns' 8-bit grids ([`columns_to_i8`]).
    pub(super) fn quantized_i8(&self) -> HeadWeights {
        self.with_layers(|d| {
            let (bytes, scales) = columns_to_i8(&d.weight, d.outputs);
            Dense {
                weight: bytes
                    .chunks_exact(d.outputs)
                    .flat_map(|row| row.iter().zip(&scales).map(|(&q, &s)| q as f32 * s))
                    .collect(),
                ..d.clone()
            }
        })
    }

    /// Each branch's hidden layers, its output weights zero-padded to `padded` (the native
    /// kernels' row stride) and its output bias; `None` when a branch has no hidden layer or one
    /// that is not `width × width` (the native kernels' tiles need both).
    pub(super) fn square_branches(&self, padded: usize) -> Option<[SquareBranch<'_>; 2]> {
        let width = self.width;
        let square = |b: &BranchWeights| {
            !b.hidden.is_empty()
                && b.hidden
                    .iter()
                    .all(|d| d.inputs == width && d.outputs == width)
        };
        self.branches.iter().all(square).then(|| {
            self.branches.each_ref().map(|b| {
                let mut output = b.output.clone();
                output.resize(padded, 0.0);
                (&b.hidden[..], output, b.output_bias)
            })
        })
    }
}
