//! The hand-written training head (`alignist::net::head_grad`) against burn's autodiff: the same
//! scores, losses and gradients (every layer of both branches, and the image features'), within
//! 1e-4 relative, for each loss, and for a branch left out of the loss.

use alignist::net::{
    DualHead, HeadConfig, Kernels, TrainingHead, contrast_loss, contrast_loss_grad, gkl_loss,
    gkl_loss_grad, ipdf_loss, ipdf_loss_grad, l1_measure_loss, l1_measure_loss_grad,
};
use burn::module::ParamId;
use burn::optim::GradientsParams;
use burn::tensor::{Device, Distribution, Tensor, TensorData};

/// A loss, the parameters' gradients, the image features' gradient, and (ours) the ids.
type Side = (f64, GradientsParams, Vec<f32>);

/// Images, rotations per image (1 500 rows: several chunks and lanes, the last chunk partial).
const B: usize = 5;
const K: usize = 300;
const IMAGE_DIM: usize = 24;
const ROTATION_DIM: usize = 18;

#[derive(Clone, Copy, Debug)]
enum Loss {
    Gkl,
    L1,
    Ipdf,
    /// GKL on the shape branch only (the feature branch left out).
    ShapeOnly,
    /// GKL with the contrast term at [`CONTRAST`], each image's uniform columns from
    /// [`UNIFORM_FROM`].
    GklContrast,
}

/// The contrast term's weight in [`Loss::GklContrast`].
const CONTRAST: f32 = 0.7;
/// The first uniform column of each image: none focused, some, most, all but one, all (the ground
/// truth alone, whose term is 0).
const UNIFORM_FROM: [usize; B] = [1, 50, 150, K - 1, K];

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
}

/// Largest magnitude.
fn scale(values: &[f32]) -> f64 {
    values.iter().fold(0f64, |m, &v| m.max(v.abs() as f64))
}

/// Largest difference over the reference's largest magnitude, or over `floor` where that is
/// smaller (a gradient that nearly cancels is compared against the loss's gradients as a whole).
fn relative(ours: &[f32], reference: &[f32], floor: f64) -> f64 {
    assert_eq!(ours.len(), reference.len());
    let diff = ours
        .iter()
        .zip(reference)
        .fold(0f64, |m, (&a, &b)| m.max((a as f64 - b as f64).abs()));
    diff / scale(reference).max(floor).max(1e-30)
}

struct Case {
    head: DualHead,
    features: Tensor<2>,
    encodings: Tensor<3>,
    log_sdf: Vec<f32>,
    log_se: Vec<f32>,
    device: Device,
}

/// A random head and batch; the targets' log-weights are drawn around `target_mean`.
fn case(seed: u64, target_mean: f32) -> Case {
    let device = alignist::backend::device().autodiff();
    device.seed(seed);
    let head = HeadConfig::new(IMAGE_DIM, ROTATION_DIM)
        .with_hidden(32)
        .with_layers(4)
        .init(&device)
        // Output biases near the targets' scale, as the trainer starts them.
        .with_output_biases(-2.0, -1.5);
    let features =
        Tensor::<2>::random([B, IMAGE_DIM], Distribution::Normal(0.0, 1.0), &device).require_grad();
    let encodings = Tensor::<3>::random([B, K, ROTATION_DIM], Distribution::Default, &device);
    let target = || {
        values(Tensor::<1>::random(
            [B * K],
            Distribution::Normal(target_mean as f64, 1.0),
            &device,
        ))
    };
    Case {
        log_sdf: target(),
        log_se: target(),
        head,
        features,
        encodings,
        device,
    }
}

/// burn's loss, gradients (by parameter id) and the features' gradient.
fn burn_side(c: &Case, loss: Loss) -> Side {
    let scores = c.head.forward(c.features.clone(), c.encodings.clone());
    let t = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [B, K]), &c.device);
    let value = match loss {
        Loss::Gkl => gkl_loss(t(&c.log_sdf), scores.shape) + gkl_loss(t(&c.log_se), scores.feature),
        Loss::L1 => {
            l1_measure_loss(t(&c.log_sdf), scores.shape)
                + l1_measure_loss(t(&c.log_se), scores.feature)
        }
        Loss::Ipdf => ipdf_loss(scores.combined()),
        Loss::ShapeOnly => gkl_loss(t(&c.log_sdf), scores.shape),
        Loss::GklContrast => {
            let log_a = t(&c.log_sdf) + t(&c.log_se);
            let contrast = contrast_loss(log_a, scores.combined(), &UNIFORM_FROM);
            gkl_loss(t(&c.log_sdf), scores.shape.clone())
                + gkl_loss(t(&c.log_se), scores.feature.clone())
                + contrast.mul_scalar(CONTRAST)
        }
    };
    let loss_value = value.clone().into_scalar::<f32>() as f64;
    let grads = value.backward();
    let d_features = values(c.features.grad(&grads).expect("the features are tracked"));
    (
        loss_value,
        GradientsParams::from_grads(grads, &c.head),
        d_features,
    )
}

/// The hand-written head's loss, gradients (registered the trainer's way) and features' gradient.
fn fused_side(c: &Case, loss: Loss, kernels: Kernels) -> (Side, Vec<(ParamId, Option<ParamId>)>) {
    let head = TrainingHead::of(&c.head, kernels);
    let pass = head.forward(
        values(c.features.clone()),
        values(c.encodings.clone()),
        B,
        K,
    );
    let [shape, feature] = pass.scores();
    let (value, d) = match loss {
        Loss::Gkl | Loss::L1 => {
            let f = if matches!(loss, Loss::Gkl) {
                gkl_loss_grad
            } else {
                l1_measure_loss_grad
            };
            let (s, f) = (f(&c.log_sdf, &shape, B), f(&c.log_se, &feature, B));
            (s.loss + f.loss, [Some(s.grad), Some(f.grad)])
        }
        Loss::Ipdf => {
            let combined: Vec<f32> = shape.iter().zip(&feature).map(|(a, b)| a + b).collect();
            let g = ipdf_loss_grad(&combined, K);
            (g.loss, [Some(g.grad.clone()), Some(g.grad)])
        }
        Loss::ShapeOnly => {
            let s = gkl_loss_grad(&c.log_sdf, &shape, B);
            (s.loss, [Some(s.grad), None])
        }
        Loss::GklContrast => {
            let sum = |a: &[f32], b: &[f32]| -> Vec<f32> {
                a.iter().zip(b).map(|(a, b)| a + b).collect()
            };
            let log_a = sum(&c.log_sdf, &c.log_se);
            let k = contrast_loss_grad(&log_a, &sum(&shape, &feature), K, &UNIFORM_FROM);
            let (s, f) = (
                gkl_loss_grad(&c.log_sdf, &shape, B),
                gkl_loss_grad(&c.log_se, &feature, B),
            );
            let with = |g: Vec<f32>| -> Vec<f32> {
                g.iter()
                    .zip(&k.grad)
                    .map(|(g, d)| g + CONTRAST * d)
                    .collect()
            };
            let loss = s.loss + f.loss + CONTRAST as f64 * k.loss;
            (loss, [Some(with(s.grad)), Some(with(f.grad))])
        }
    };
    let grads = head.backward(&pass, d.each_ref().map(|d| d.as_deref()));
    let d_features = grads.features.clone();
    let mut params = GradientsParams::new();
    let ids = head.param_ids().to_vec();
    grads.register(&head, &mut params, &c.device);
    ((value, params, d_features), ids)
}

/// [`check_on`] on each library GEMM: the `gemm` crate (`widest`) and matrixmultiply (`avx2`,
/// `portable`).
fn check(loss: Loss, seed: u64) {
    for kernels in [Kernels::Widest, Kernels::Avx2, Kernels::Portable] {
        check_on(loss, seed, kernels);
    }
}

fn check_on(loss: Loss, seed: u64, kernels: Kernels) {
    // L1's gradient jumps where a score meets its target (the sign of `exp(s) − a`), where f32
    // and f64 may disagree: its targets are drawn well below the scores (output biases ≈ −2).
    let target_mean = if matches!(loss, Loss::L1) { -8.0 } else { -2.0 };
    let c = case(seed, target_mean);
    let (burn_loss, mut burn_grads, burn_df) = burn_side(&c, loss);
    let ((our_loss, mut our_grads, our_df), ids) = fused_side(&c, loss, kernels);
    assert!(
        (our_loss - burn_loss).abs() <= 1e-4 * burn_loss.abs().max(1.0),
        "{loss:?}: loss {our_loss} against burn's {burn_loss}"
    );
    // A hundredth of the largest gradient anywhere: the floor of the relative comparisons.
    let floor = 1e-2 * scale(&burn_df).max(burn_weight_scale(&burn_grads, &ids));
    let e = relative(&our_df, &burn_df, floor);
    assert!(
        e <= 1e-4,
        "{loss:?}: image features' gradient off by {e:.2e}"
    );
    let mut compared = 0;
    for (i, (w, b)) in ids.iter().enumerate() {
        let ours_w = our_grads.remove::<2>(*w).map(values);
        let burn_w = burn_grads.remove::<2>(*w).map(values);
        match (ours_w, burn_w) {
            (Some(o), Some(r)) => {
                let e = relative(&o, &r, floor);
                assert!(
                    e <= 1e-4,
                    "{loss:?}: layer {i}'s weight gradient off by {e:.2e}"
                );
                compared += 1;
            }
            (None, None) => {}
            (o, r) => panic!(
                "{loss:?}: layer {i}: ours has a weight gradient {}, burn {}",
                o.is_some(),
                r.is_some()
            ),
        }
        if let Some(b) = b {
            match (
                our_grads.remove::<1>(*b).map(values),
                burn_grads.remove::<1>(*b).map(values),
            ) {
                (Some(o), Some(r)) if matches!(loss, Loss::Ipdf) && r.len() == 1 => {
                    // IPDF's output biases: zero in exact arithmetic (each softmax row sums to
                    // one); both sides must be within f32 summation error of it.
                    assert!(
                        scale(&o) <= 1e-6 && scale(&r) <= 1e-6,
                        "{loss:?}: layer {i}'s bias gradient {o:?}, burn's {r:?}"
                    );
                }
                (Some(o), Some(r)) => {
                    let e = relative(&o, &r, floor);
                    assert!(
                        e <= 1e-4,
                        "{loss:?}: layer {i}'s bias gradient off by {e:.2e}"
                    );
                }
                (None, None) => {}
                _ => panic!("{loss:?}: layer {i}: bias gradients on one side only"),
            }
        }
    }
    // image + rotation + 4 layers per branch in the loss.
    let expected = 2 + if matches!(loss, Loss::ShapeOnly) {
        4
    } else {
        8
    };
    assert_eq!(compared, expected, "{loss:?}: layers compared");
    assert!(
        burn_grads.is_empty(),
        "{loss:?}: burn has gradients we do not"
    );
}

/// The largest weight gradient of any layer.
fn burn_weight_scale(grads: &GradientsParams, ids: &[(ParamId, Option<ParamId>)]) -> f64 {
    ids.iter()
        .filter_map(|(w, _)| grads.get::<2>(*w))
        .map(|g| scale(&values(g)))
        .fold(0.0, f64::max)
}

#[test]
fn generalised_kl_gradients_equal_burns_autodiff() {
    check(Loss::Gkl, 11);
}

#[test]
fn l1_measure_gradients_equal_burns_autodiff() {
    check(Loss::L1, 12);
}

#[test]
fn ipdf_gradients_equal_burns_autodiff() {
    check(Loss::Ipdf, 13);
}

#[test]
fn contrast_term_gradients_equal_burns_autodiff() {
    check(Loss::GklContrast, 16);
}

/// The contrast term alone: 0 where the scores are the targets up to a constant on the term's
/// columns (whatever the masked columns hold), positive otherwise; its gradient is 0 on the
/// masked columns and sums to 0 on each row.
#[test]
fn the_contrast_term_vanishes_at_the_targets_and_ignores_the_focused_columns() {
    let k = 6;
    let log_a = [0.0, -3.0, -1.0, -2.0, -5.0, -0.5];
    let uniform_from = [3];
    let mut c: Vec<f32> = log_a.iter().map(|a| a + 4.0).collect();
    c[1] = 40.0; // a focused column: not in the term
    c[2] = -40.0;
    let at = contrast_loss_grad(&log_a, &c, k, &uniform_from);
    assert!(at.loss.abs() < 1e-9, "loss {} at the targets", at.loss);
    assert!(at.grad.iter().all(|g| g.abs() < 1e-6), "{:?}", at.grad);
    c[4] += 2.0;
    let off = contrast_loss_grad(&log_a, &c, k, &uniform_from);
    assert!(off.loss > 1e-3, "loss {} off the targets", off.loss);
    assert_eq!((off.grad[1], off.grad[2]), (0.0, 0.0));
    assert!(
        off.grad[4] > 0.0,
        "the raised column is pushed down: {:?}",
        off.grad
    );
    assert!(off.grad.iter().sum::<f32>().abs() < 1e-6);
}

#[test]
fn a_branch_left_out_of_the_loss_gets_no_gradient() {
    check(Loss::ShapeOnly, 14);
}

#[test]
fn the_gradients_do_not_depend_on_the_thread_count() {
    let c = case(15, -2.0);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let head = TrainingHead::of(&c.head, Kernels::default());
                let pass = head.forward(
                    values(c.features.clone()),
                    values(c.encodings.clone()),
                    B,
                    K,
                );
                let [shape, feature] = pass.scores();
                let d = [
                    gkl_loss_grad(&c.log_sdf, &shape, B).grad,
                    gkl_loss_grad(&c.log_se, &feature, B).grad,
                ];
                head.backward(&pass, [Some(&d[0][..]), Some(&d[1][..])])
            })
    };
    assert_eq!(
        run(1),
        run(3),
        "one thread and three give different gradients"
    );
}
