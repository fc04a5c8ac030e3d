//! The hand-written training encoder (`alignist::net::encoder_grad`) against burn's autodiff
//! through `Encoder::forward`: the same features, the same gradients of every convolution and
//! BatchNorm (within 1e-4 relative), and the same running statistics after the step.

use alignist::net::{
    Encoder, EncoderConfig, Kernels, ResNetLayout, TrainingEncoder, images_tensor,
};
use burn::module::Module;
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};

const IMAGES: usize = 3;
const SIZE: usize = 16;

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
}

/// Largest difference over the reference's largest magnitude (at least `floor`).
fn relative(ours: &[f32], reference: &[f32], floor: f32) -> f32 {
    assert_eq!(ours.len(), reference.len());
    let diff = ours
        .iter()
        .zip(reference)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    let scale = reference.iter().fold(floor, |m, v| m.max(v.abs()));
    diff / scale
}

/// A small deterministic stream of numbers in [0, 1).
fn stream(seed: u64, n: usize) -> Vec<f32> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect()
}

/// Two encoders of `layout`, pooled over a `grid × grid` grid, with the same weights and
/// statistics, each with its own running state (a copy through the record: two seeded inits do
/// not draw the same weights). A `tiny_deep` one is a `tiny` one deepened, its added blocks at
/// their identity start; a `tiny_wide` one is a `tiny` one grown, its added channels unread.
fn encoders(device: &Device, seed: u64, layout: ResNetLayout, grid: usize) -> (Encoder, Encoder) {
    device.seed(seed);
    let tiny = EncoderConfig::new(ResNetLayout::Tiny).init(device);
    let reference = tiny
        .grown(ResNetLayout::Tiny, layout, device)
        .unwrap()
        .with_pool_grid(grid);
    let copy = EncoderConfig::new(layout)
        .with_pool_grid(grid)
        .init(device)
        .load_record(reference.clone().into_record());
    (reference, copy)
}

#[test]
fn the_hand_written_encoder_trains_as_burns_autodiff() {
    // 16 px: every stage halves evenly; 9 px: odd sides, windows cut by the edges (9, 5, 3, 2).
    for size in [SIZE, 9] {
        check(size, ResNetLayout::Tiny, 1);
    }
    // Blocks at their identity start: zero scale and shift, gradients through them all the same.
    check(SIZE, ResNetLayout::TinyDeep, 1);
    // Added channels: weights from them into the old channels zero, 24 channels a stem.
    check(SIZE, ResNetLayout::TinyWide, 1);
}

#[test]
fn the_hand_written_grid_pooling_trains_as_burns_autodiff() {
    // 32 px ends in a 4 × 4 map: 2 × 2 cells of 2 × 2 pixels. On the 2 × 2 map of 16 px, a 3 × 3
    // grid's cells overlap (burn's adaptive bins), and a 2 × 2 grid keeps every pixel.
    check(32, ResNetLayout::Tiny, 2);
    check(SIZE, ResNetLayout::Tiny, 3);
    check(9, ResNetLayout::TinyDeep, 2);
}

fn check(size: usize, layout: ResNetLayout, grid: usize) {
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv).autodiff();
    let (reference, ours) = encoders(&device, 5, layout, grid);
    let crops: Vec<Vec<u8>> = (0..IMAGES)
        .map(|i| {
            stream(i as u64 + 1, size * size * 3)
                .iter()
                .map(|v| (v * 255.0) as u8)
                .collect()
        })
        .collect();
    let crops: Vec<&[u8]> = crops.iter().map(|c| c.as_slice()).collect();
    let dim = EncoderConfig::new(layout)
        .with_pool_grid(grid)
        .feature_dim();
    let d: Vec<f32> = stream(99, IMAGES * dim).iter().map(|v| v - 0.5).collect();

    // burn: the loss Σ F ⊙ d, whose gradient with respect to the features is d.
    let features = reference.forward(images_tensor(&crops, size, &device));
    let d_tensor = Tensor::<2>::from_data(TensorData::new(d.clone(), [IMAGES, dim]), &device);
    let burn_features = values(features.clone());
    let mut burn_grads =
        GradientsParams::from_grads((features * d_tensor).sum().backward(), &reference);

    let model =
        TrainingEncoder::of(&ours, Kernels::default()).expect("the tiny layout runs by hand");
    let pass = model.forward(&crops, size);
    let e = relative(pass.features(), &burn_features, 1e-6);
    assert!(
        e <= 1e-4,
        "{layout:?} {size} px, grid {grid}: features off by {e:.2e}"
    );
    let grads = model.backward(&pass, &d);
    let mut our_grads = GradientsParams::new();
    let ours_ids = model.param_ids();
    grads.register(&model, &ours, &mut our_grads, &device);

    let reference_ids = TrainingEncoder::of(&reference, Kernels::default())
        .unwrap()
        .param_ids();
    let blocks: usize = if layout == ResNetLayout::Tiny { 4 } else { 8 };
    assert_eq!(
        reference_ids.len(),
        1 + 2 * blocks + 3,
        "stem, two per block, three shortcuts"
    );
    for (unit, (r, o)) in reference_ids.iter().zip(&ours_ids).enumerate() {
        let pairs = [
            (
                burn_grads.remove::<4>(r[0]).map(values),
                our_grads.remove::<4>(o[0]).map(values),
            ),
            (
                burn_grads.remove::<1>(r[1]).map(values),
                our_grads.remove::<1>(o[1]).map(values),
            ),
            (
                burn_grads.remove::<1>(r[2]).map(values),
                our_grads.remove::<1>(o[2]).map(values),
            ),
        ];
        for (which, pair) in ["weight", "gamma", "beta"].iter().zip(pairs) {
            let (Some(r), Some(o)) = pair else {
                panic!("{layout:?} {size} px, unit {unit}: a {which} gradient is missing");
            };
            let e = relative(&o, &r, 1e-3);
            assert!(
                e <= 1e-4,
                "{layout:?} {size} px, grid {grid}, unit {unit}: {which} gradient off by {e:.2e}"
            );
        }
    }

    // The running statistics: the same features in inference mode, which reads them.
    let inner = device.clone().inner();
    let inference = |e: &Encoder| {
        e.sync_running_stats();
        values(
            e.clone()
                .valid()
                .forward(images_tensor(&crops, size, &inner)),
        )
    };
    let e = relative(&inference(&ours), &inference(&reference), 1e-6);
    assert!(
        e <= 1e-4,
        "{layout:?} {size} px: inference features (running statistics) off by {e:.2e}"
    );
}

#[test]
fn layouts_with_a_stem_pool_are_left_to_burn() {
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv).autodiff();
    let resnet18 = EncoderConfig::new(ResNetLayout::Resnet18).init(&device);
    assert!(TrainingEncoder::of(&resnet18, Kernels::default()).is_none());
}

#[test]
fn the_encoder_gradients_do_not_depend_on_the_thread_count() {
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv).autodiff();
    let (a, b) = encoders(&device, 8, ResNetLayout::Tiny, 1);
    let crops: Vec<Vec<u8>> = (0..7)
        .map(|i| {
            stream(i + 40, SIZE * SIZE * 3)
                .iter()
                .map(|v| (v * 255.0) as u8)
                .collect()
        })
        .collect();
    let crops: Vec<&[u8]> = crops.iter().map(|c| c.as_slice()).collect();
    let d: Vec<f32> = stream(3, 7 * ResNetLayout::Tiny.feature_dim());
    let run = |encoder: &Encoder, threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let model = TrainingEncoder::of(encoder, Kernels::default()).unwrap();
            let pass = model.forward(&crops, SIZE);
            (pass.features().to_vec(), model.backward(&pass, &d).units)
        })
    };
    let (one, three) = (run(&a, 1), run(&b, 3));
    assert_eq!(one.0, three.0, "features");
    assert_eq!(one.1, three.1, "gradients");
}
