//! Losses between the predicted log-weights `s` and the expert targets `a = exp(log_a)` on the
//! K sampled rotations of each image (`[B, K]` tensors), averaged over images.

use burn::tensor::activation::{log_softmax, softmax};
use burn::tensor::{Tensor, TensorData};

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

/// What the contrast term adds to a masked-out column's logit: far enough below every score that
/// its softmax share is exactly 0, finite so that `0 · log 0` stays 0.
const MASKED: f32 = -1.0e4;

/// The contrast term (ours, a run's `TrainConfig::contrast`): IPDF's softmax, taken over
/// each row's ground truth (column 0) and its uniformly drawn rotations (columns
/// `uniform_from[b]..K`), fitted to the experts' combined measure normalised over the same columns:
/// `KL(p ‖ softmax(c))` with `p ∝ a`. The GKL of Eq. 5 lets a wrong pose keep any score whose
/// `exp` is small; this term makes the truth outscore the uniform rotations, as a classifier's
/// cross-entropy does. Its columns are drawn uniformly, so `p` is the measure's own shape there,
/// symmetric equivalents included. `log_a` and `c` are `[B, K]`.
pub fn contrast_loss(log_a: Tensor<2>, c: Tensor<2>, uniform_from: &[usize]) -> Tensor<1> {
    let [b, k] = c.dims();
    let mask: Vec<f32> = uniform_from
        .iter()
        .flat_map(|&u| (0..k).map(move |j| if j == 0 || j >= u { 0.0 } else { MASKED }))
        .collect();
    let mask = Tensor::<2>::from_data(TensorData::new(mask, [b, k]), &c.device());
    let log_p = log_softmax(log_a + mask.clone(), 1);
    let p = softmax(log_p.clone(), 1);
    let log_q = log_softmax(c + mask, 1);
    (p * (log_p - log_q)).sum_dim(1).mean()
}

/// [`contrast_loss`] and its gradient `∂/∂c_bj = (softmax(c)_j − p_j) / B` on each row's columns
/// (0 on the masked ones), for rows of `k` scores.
pub fn contrast_loss_grad(log_a: &[f32], c: &[f32], k: usize, uniform_from: &[usize]) -> LossGrad {
    let scale = 1.0 / uniform_from.len().max(1) as f64;
    let mut loss = 0.0f64;
    let mut grad = vec![0f32; c.len()];
    let rows = log_a.chunks_exact(k).zip(c.chunks_exact(k));
    for ((row, (log_a, c)), &u) in grad.chunks_exact_mut(k).zip(rows).zip(uniform_from) {
        let columns = || std::iter::once(0).chain(u.min(k).max(1)..k);
        let log_sum = |v: &[f32]| {
            let max = columns()
                .map(|j| v[j] as f64)
                .fold(f64::NEG_INFINITY, f64::max);
            max + columns()
                .map(|j| (v[j] as f64 - max).exp())
                .sum::<f64>()
                .ln()
        };
        let (a_sum, c_sum) = (log_sum(log_a), log_sum(c));
        for j in columns() {
            let log_p = log_a[j] as f64 - a_sum;
            let log_q = c[j] as f64 - c_sum;
            let p = log_p.exp();
            loss += p * (log_p - log_q);
            row[j] = ((log_q.exp() - p) * scale) as f32;
        }
    }
    LossGrad {
        loss: loss * scale,
        grad,
    }
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
