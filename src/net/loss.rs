//! Losses between the predicted log-weights `s` and the expert targets `a = exp(log_a)` on the
//! K sampled rotations of each image (`[B, K]` tensors), averaged over images.

use burn::tensor::Tensor;
use burn::tensor::activation::log_softmax;

/// Generalised KL divergence between the target measure `a` and the predicted `exp(s)` (paper
/// Eq. 5): `GKL(a‖exp s) = Σ_k [a_k (log a_k − s_k) + exp(s_k) − a_k]`. It is 0 exactly when
/// `s = log a` and positive otherwise; unlike KL it also fits the measures' total mass.
pub fn gkl_loss(log_a: Tensor<2>, s: Tensor<2>) -> Tensor<1> {
    let a = log_a.clone().exp();
    let per_rotation = a.clone() * (log_a - s.clone()) + s.exp() - a;
    per_rotation.sum_dim(1).mean()
}

/// L1 distance between the measures, `Σ_k |exp(s_k) − a_k|` (the paper's ablation).
pub fn l1_measure_loss(log_a: Tensor<2>, s: Tensor<2>) -> Tensor<1> {
    (s.exp() - log_a.exp()).abs().sum_dim(1).mean()
}

/// IPDF's loss: `−log softmax(s)` at the ground truth, which is column 0 of every row (the
/// other columns are uniformly sampled rotations).
pub fn ipdf_loss(s: Tensor<2>) -> Tensor<1> {
    let [b, _] = s.dims();
    log_softmax(s, 1).narrow(1, 0, 1).reshape([b]).neg().mean()
}
