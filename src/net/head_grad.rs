//! The dual-branch head's forward and backward for training, by hand (paper Sec. 3.3; the
//! losses' gradients are in [`super::loss`]): the arithmetic of burn's autodiff through
//! [`DualHead::forward`], on plain row-major f32 matrices and the library GEMM (`dense::gemm`:
//! 512-bit where the core has AVX-512 unless `ALIGNIST_KERNELS` caps it), without the
//! autodiff graph's per-op tensors.
//!
//! Forward, per chunk of rows (a rotation of an image): `x₀ = relu(enc·W_R + b_R + f·W_I + b_I)`,
//! then per branch `h_l = relu(h_{l−1}·W_l + b_l)` and the linear output `s = h·w + b`. Every
//! activation is kept for the backward pass. Backward, per chunk: `dZ_l = dH_l ⊙ [h_l > 0]`,
//! `dW_l += H_{l−1}ᵀ·dZ_l`, `db_l += Σ_rows dZ_l`, `dH_{l−1} = dZ_l·W_lᵀ`; the two branches' `dx₀`
//! are summed before `x₀`'s ReLU mask; the image half's rows are summed per image, and the image
//! features' gradient `dF = dImg·W_Iᵀ` goes back into the encoder through burn (the trainer's
//! job). Weight gradients are summed in a fixed number of lanes, in a fixed order, so a step's
//! result does not depend on how many threads ran it.

use burn::module::ParamId;
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use super::DualHead;
use super::dense::{Dense, Strided, gemm};
use super::kernels::Kernels;

/// Rows of one task (a chunk's activations, 7 × 256 rows × 256 × 4 B, stay in a core's L2).
const CHUNK_ROWS: usize = 512;

/// Lanes the weight gradients are summed in: each lane runs its chunks in order into its own
/// sums, and the lanes are added in order at the end (deterministic for any thread count).
const LANES: usize = 8;

/// The head's weights, read from a [`DualHead`] for one training step, with the parameter ids
/// their gradients are registered under.
#[derive(Debug, Clone)]
pub struct TrainingHead {
    image: Dense,
    rotation: Dense,
    /// Per branch (shape, feature): the hidden layers, then the output layer (`width → 1`).
    branches: [Vec<Dense>; 2],
    /// Weight and bias ids in the order image, rotation, shape layers, feature layers.
    ids: Vec<(ParamId, Option<ParamId>)>,
    /// The library GEMM's kernels.
    kernels: Kernels,
}

/// One chunk's activations.
#[derive(Debug)]
struct ChunkPass {
    start: usize,
    rows: usize,
    x0: Vec<f32>,
    /// Per branch, the outputs of its hidden layers (each `[rows, width]`, after ReLU).
    hidden: [Vec<Vec<f32>>; 2],
    scores: [Vec<f32>; 2],
}

/// A forward pass, kept for its backward.
#[derive(Debug)]
pub struct HeadPass {
    images: usize,
    per_image: usize,
    features: Vec<f32>,
    encodings: Vec<f32>,
    chunks: Vec<ChunkPass>,
}

impl HeadPass {
    /// Each branch's scores (`s_θ`, `s_φ`), `[images · per_image]` row-major.
    pub fn scores(&self) -> [Vec<f32>; 2] {
        [0, 1].map(|b| {
            self.chunks
                .iter()
                .flat_map(|c| c.scores[b].iter().copied())
                .collect()
        })
    }
}

/// One layer's gradient.
#[derive(Debug, Clone, PartialEq)]
pub struct LayerGrad {
    /// `[inputs, outputs]`, row-major.
    pub weight: Vec<f32>,
    /// `[outputs]`.
    pub bias: Vec<f32>,
}

impl LayerGrad {
    fn zeros(layer: &Dense) -> Self {
        LayerGrad {
            weight: vec![0.0; layer.inputs * layer.outputs],
            bias: vec![0.0; layer.outputs],
        }
    }

    fn add(&mut self, other: &LayerGrad) {
        for (a, b) in self.weight.iter_mut().zip(&other.weight) {
            *a += b;
        }
        for (a, b) in self.bias.iter_mut().zip(&other.bias) {
            *a += b;
        }
    }

    /// `dW += inputᵀ·dz`, `db += Σ_rows dz` for `rows` rows.
    fn accumulate(&mut self, kernels: Kernels, input: &[f32], dz: &[f32], rows: usize) {
        let (inputs, outputs) = (self.weight.len() / self.bias.len(), self.bias.len());
        gemm(
            kernels,
            [inputs, rows, outputs],
            Strided::columns(input, inputs),
            Strided::rows(dz, outputs),
            1.0,
            &mut self.weight,
        );
        for row in dz[..rows * outputs].chunks_exact(outputs) {
            for (b, d) in self.bias.iter_mut().zip(row) {
                *b += d;
            }
        }
    }
}

/// The gradients of one step, in [`TrainingHead`]'s parameter order; a branch left out of the
/// loss has none (as in burn, where it is not in the graph).
#[derive(Debug, Clone, PartialEq)]
pub struct HeadGrads {
    /// Per layer: image, rotation, the shape branch's, the feature branch's.
    pub layers: Vec<Option<LayerGrad>>,
    /// The loss's gradient with respect to the image features, `[images, image_dim]`.
    pub features: Vec<f32>,
}

/// One lane's sums: the rotation layer, each branch's layers (when in the loss), and the image
/// half's gradient per image.
struct LaneSums {
    rotation: LayerGrad,
    branches: [Option<Vec<LayerGrad>>; 2],
    image_rows: Vec<f32>,
}

fn relu_in_place(x: &mut [f32]) {
    for v in x {
        *v = v.max(0.0);
    }
}

/// `d ← d ⊙ [activation > 0]`: the ReLU's backward.
fn mask_by(d: &mut [f32], activation: &[f32]) {
    // Branch-free (a select the compiler vectorises): a branch per element, taken at random by
    // half the units, cost more than the GEMM beside it.
    for (d, a) in d.iter_mut().zip(activation) {
        *d = if *a > 0.0 { *d } else { 0.0 };
    }
}

impl TrainingHead {
    /// Reads `head`'s current weights, for GEMMs on `kernels`.
    pub fn of(head: &DualHead, kernels: Kernels) -> Self {
        let (image, rotation, shape, feature) = head.parts();
        let mut ids = vec![ids_of(image), ids_of(rotation)];
        let branches = [shape, feature].map(|b| {
            let (hidden, output) = b.layers();
            hidden
                .iter()
                .chain(std::iter::once(output))
                .map(Dense::of)
                .collect::<Vec<_>>()
        });
        for b in [shape, feature] {
            let (hidden, output) = b.layers();
            ids.extend(hidden.iter().chain(std::iter::once(output)).map(ids_of));
        }
        TrainingHead {
            image: Dense::of(image),
            rotation: Dense::of(rotation),
            branches,
            ids,
            kernels,
        }
    }

    /// Each layer's weight and bias ids, in [`HeadGrads::layers`]' order.
    pub fn param_ids(&self) -> &[(ParamId, Option<ParamId>)] {
        &self.ids
    }

    /// The forward pass over `images` images (`features`, `[images, image_dim]`) and
    /// `per_image` rotations of each (`encodings`, `[images · per_image, rotation_dim]`).
    pub fn forward(
        &self,
        features: Vec<f32>,
        encodings: Vec<f32>,
        images: usize,
        per_image: usize,
    ) -> HeadPass {
        let width = self.rotation.outputs;
        let e = self.rotation.inputs;
        assert_eq!(features.len(), images * self.image.inputs, "image features");
        assert_eq!(
            encodings.len(),
            images * per_image * e,
            "rotation encodings"
        );
        let mut image_term = vec![0.0; images * width];
        self.image
            .apply(self.kernels, &features, images, &mut image_term);
        let chunks = encodings
            .par_chunks(CHUNK_ROWS * e)
            .enumerate()
            .map(|(c, enc)| {
                let (start, rows) = (c * CHUNK_ROWS, enc.len() / e);
                let mut x0 = vec![0.0; rows * width];
                self.rotation.apply(self.kernels, enc, rows, &mut x0);
                for (r, row) in x0.chunks_exact_mut(width).enumerate() {
                    let image = &image_term[(start + r) / per_image * width..][..width];
                    for (x, i) in row.iter_mut().zip(image) {
                        *x = (*x + i).max(0.0);
                    }
                }
                let branch = |layers: &[Dense]| {
                    let (hidden, output) = layers.split_at(layers.len() - 1);
                    let mut outs: Vec<Vec<f32>> = Vec::with_capacity(hidden.len());
                    for layer in hidden {
                        let mut h = vec![0.0; rows * layer.outputs];
                        layer.apply(self.kernels, outs.last().unwrap_or(&x0), rows, &mut h);
                        relu_in_place(&mut h);
                        outs.push(h);
                    }
                    let mut s = vec![0.0; rows];
                    output[0].apply(self.kernels, outs.last().unwrap_or(&x0), rows, &mut s);
                    (outs, s)
                };
                let (shape_hidden, shape) = branch(&self.branches[0]);
                let (feature_hidden, feature) = branch(&self.branches[1]);
                ChunkPass {
                    start,
                    rows,
                    x0,
                    hidden: [shape_hidden, feature_hidden],
                    scores: [shape, feature],
                }
            })
            .collect();
        HeadPass {
            images,
            per_image,
            features,
            encodings,
            chunks,
        }
    }

    /// The backward pass of `pass` for the loss's gradients with respect to each branch's scores
    /// (`None`: the branch is not in the loss).
    pub fn backward(&self, pass: &HeadPass, d_scores: [Option<&[f32]>; 2]) -> HeadGrads {
        let n = pass.images * pass.per_image;
        for d in d_scores.iter().flatten() {
            assert_eq!(d.len(), n, "one score gradient per row");
        }
        let per_lane = pass.chunks.len().div_ceil(LANES).max(1);
        let lanes: Vec<LaneSums> = pass
            .chunks
            .par_chunks(per_lane)
            .map(|chunks| {
                let mut sums = LaneSums {
                    rotation: LayerGrad::zeros(&self.rotation),
                    branches: [0, 1].map(|b| {
                        d_scores[b].map(|_| self.branches[b].iter().map(LayerGrad::zeros).collect())
                    }),
                    image_rows: vec![0.0; pass.images * self.rotation.outputs],
                };
                for chunk in chunks {
                    self.backward_chunk(pass, chunk, d_scores, &mut sums);
                }
                sums
            })
            .collect();
        let mut lanes = lanes.into_iter();
        let mut total = lanes.next().expect("a pass has at least one lane");
        for lane in lanes {
            total.rotation.add(&lane.rotation);
            for (t, l) in total.branches.iter_mut().zip(&lane.branches) {
                if let (Some(t), Some(l)) = (t, l) {
                    t.iter_mut().zip(l).for_each(|(t, l)| t.add(l));
                }
            }
            for (t, l) in total.image_rows.iter_mut().zip(&lane.image_rows) {
                *t += l;
            }
        }
        let mut image = LayerGrad::zeros(&self.image);
        image.accumulate(self.kernels, &pass.features, &total.image_rows, pass.images);
        let mut features = vec![0.0; pass.images * self.image.inputs];
        gemm(
            self.kernels,
            [pass.images, self.image.outputs, self.image.inputs],
            Strided::rows(&total.image_rows, self.image.outputs),
            self.image.transposed(),
            0.0,
            &mut features,
        );
        let [shape, feature] = total.branches;
        let mut layers = vec![Some(image), Some(total.rotation)];
        for (branch, grads) in self.branches.iter().zip([shape, feature]) {
            match grads {
                Some(g) => layers.extend(g.into_iter().map(Some)),
                None => layers.extend(branch.iter().map(|_| None)),
            }
        }
        HeadGrads { layers, features }
    }

    fn backward_chunk(
        &self,
        pass: &HeadPass,
        chunk: &ChunkPass,
        d_scores: [Option<&[f32]>; 2],
        sums: &mut LaneSums,
    ) {
        let width = self.rotation.outputs;
        let rows = chunk.rows;
        let mut dx0 = vec![0.0; rows * width];
        let branches = d_scores
            .iter()
            .zip(sums.branches.iter_mut())
            .zip(self.branches.iter().zip(&chunk.hidden));
        for ((d, grads), (layers, hidden)) in branches {
            let (Some(d), Some(grads)) = (d, grads.as_mut()) else {
                continue;
            };
            let inputs: Vec<&[f32]> = std::iter::once(&chunk.x0[..])
                .chain(hidden.iter().map(|h| &h[..]))
                .collect();
            let mut dz = d[chunk.start..chunk.start + rows].to_vec();
            for l in (0..layers.len()).rev() {
                let layer = &layers[l];
                grads[l].accumulate(self.kernels, inputs[l], &dz, rows);
                let transposed = [rows, layer.outputs, layer.inputs];
                if l == 0 {
                    gemm(
                        self.kernels,
                        transposed,
                        Strided::rows(&dz, layer.outputs),
                        layer.transposed(),
                        1.0,
                        &mut dx0,
                    );
                } else {
                    let mut previous = vec![0.0; rows * layer.inputs];
                    gemm(
                        self.kernels,
                        transposed,
                        Strided::rows(&dz, layer.outputs),
                        layer.transposed(),
                        0.0,
                        &mut previous,
                    );
                    mask_by(&mut previous, inputs[l]);
                    dz = previous;
                }
            }
        }
        mask_by(&mut dx0, &chunk.x0);
        let e = self.rotation.inputs;
        let enc = &pass.encodings[chunk.start * e..(chunk.start + rows) * e];
        sums.rotation.accumulate(self.kernels, enc, &dx0, rows);
        for (r, row) in dx0.chunks_exact(width).enumerate() {
            let image = (chunk.start + r) / pass.per_image;
            for (t, d) in sums.image_rows[image * width..][..width]
                .iter_mut()
                .zip(row)
            {
                *t += d;
            }
        }
    }
}

fn ids_of(linear: &burn::nn::Linear) -> (ParamId, Option<ParamId>) {
    (linear.weight.id, linear.bias.as_ref().map(|b| b.id))
}

impl HeadGrads {
    /// Registers every gradient under its parameter's id in `grads`, as tensors on `device`'s
    /// plain (non-autodiff) side, where burn's optimisers read them.
    pub fn register(self, head: &TrainingHead, grads: &mut GradientsParams, device: &Device) {
        let device = device.clone().inner();
        let dense = std::iter::once(&head.image)
            .chain(std::iter::once(&head.rotation))
            .chain(head.branches.iter().flatten());
        for ((grad, (weight_id, bias_id)), layer) in
            self.layers.into_iter().zip(&head.ids).zip(dense)
        {
            let Some(grad) = grad else { continue };
            let w = TensorData::new(grad.weight, [layer.inputs, layer.outputs]);
            grads.register::<2>(*weight_id, Tensor::from_data(w, &device));
            if let Some(bias_id) = bias_id {
                let b = TensorData::new(grad.bias, [layer.outputs]);
                grads.register::<1>(*bias_id, Tensor::from_data(b, &device));
            }
        }
    }
}
