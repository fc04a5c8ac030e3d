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

/// A loss over `[B, K]` scores and its gradient with respect to every score: what the
/// hand-written training head ([`super::head_grad`]) back-propagates.
#[derive(Debug, Clone, PartialEq)]
pub struct LossGrad {
    /// The loss (mean over images).
    pub loss: f64,
    /// `∂loss/∂s`, `[B, K]` row-major.
    pub grad: Vec<f32>,
}

/// [`gkl_loss`] (paper Eq. 5) and its gradient `∂/∂s_k = (exp(s_k) − a_k) / B`, for `images`
/// rows of scores.
pub fn gkl_loss_grad(log_a: &[f32], s: &[f32], images: usize) -> LossGrad {
    measure_loss_grad(log_a, s, images, |log_a, s, a, e| {
        (a * (log_a - s) + e - a, e - a)
    })
}

/// [`l1_measure_loss`] and its gradient `∂/∂s_k = sign(exp(s_k) − a_k)·exp(s_k) / B`.
pub fn l1_measure_loss_grad(log_a: &[f32], s: &[f32], images: usize) -> LossGrad {
    measure_loss_grad(log_a, s, images, |_, _, a, e| {
        ((e - a).abs(), (e - a).signum() * e)
    })
}

/// A loss between measures that sums one term per rotation, averaged over `images`:
/// `term(log a, s, a, exp s)` gives the term and its derivative in `s` (in f64).
fn measure_loss_grad(
    log_a: &[f32],
    s: &[f32],
    images: usize,
    term: impl Fn(f64, f64, f64, f64) -> (f64, f64),
) -> LossGrad {
    let scale = 1.0 / images.max(1) as f64;
    let mut loss = 0.0f64;
    let grad = log_a
        .iter()
        .zip(s)
        .map(|(&log_a, &s)| {
            let (log_a, s) = (log_a as f64, s as f64);
            let (value, derivative) = term(log_a, s, log_a.exp(), s.exp());
            loss += value;
            (derivative * scale) as f32
        })
        .collect();
    LossGrad {
        loss: loss * scale,
        grad,
    }
}

/// [`ipdf_loss`] and its gradient `∂/∂s_bk = (softmax(s_b)_k − [k = 0]) / B`, for rows of `k`
/// scores (the ground truth in column 0).
pub fn ipdf_loss_grad(s: &[f32], k: usize) -> LossGrad {
    let images = s.len() / k.max(1);
    let scale = 1.0 / images.max(1) as f64;
    let mut loss = 0.0f64;
    let mut grad = Vec::with_capacity(s.len());
    for row in s.chunks_exact(k) {
        let max = row.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v)) as f64;
        let sum: f64 = row.iter().map(|&v| (v as f64 - max).exp()).sum();
        let log_sum = max + sum.ln();
        loss += log_sum - row[0] as f64;
        grad.extend(row.iter().enumerate().map(|(j, &v)| {
            let p = (v as f64 - log_sum).exp();
            ((p - if j == 0 { 1.0 } else { 0.0 }) * scale) as f32
        }));
    }
    LossGrad {
        loss: loss * scale,
        grad,
    }
}
