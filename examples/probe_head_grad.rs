//! The hand-written training head's forward and backward (`net::head_grad`) at the bench's shape
//! (batch 16, K 256, hidden 256, 4 layers, cube encoding): ms per pass, best and median of 30,
//! and GFLOP/s of the backward's GEMMs. For profiling (`perf record`) the training head alone.
//! `cargo run --release --example probe_head_grad`
use std::time::Instant;

use alignist::net::{HeadConfig, TrainingHead};
use burn::tensor::{Distribution, Tensor};

fn main() {
    let (images, per_image, image_dim, width, layers) = (16usize, 256usize, 128usize, 256, 4);
    let encoding = alignist::encoding::RotationEncoding::Cube.dim();
    let device = alignist::backend::device();
    device.seed(1);
    let head = HeadConfig::new(image_dim, encoding)
        .with_hidden(width)
        .with_layers(layers)
        .init(&device);
    let values = |t: Tensor<2>| t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
    let features = values(Tensor::random(
        [images, image_dim],
        Distribution::Normal(0.0, 1.0),
        &device,
    ));
    let encodings = values(Tensor::random(
        [images * per_image, encoding],
        Distribution::Default,
        &device,
    ));
    let d = values(Tensor::random(
        [1, images * per_image],
        Distribution::Normal(0.0, 1e-3),
        &device,
    ));
    let training = TrainingHead::of(&head, alignist::net::Kernels::default());
    let (mut forward, mut backward) = (Vec::new(), Vec::new());
    for _ in 0..35 {
        let t = Instant::now();
        let pass = training.forward(features.clone(), encodings.clone(), images, per_image);
        forward.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        let grads = training.backward(&pass, [Some(&d), Some(&d)]);
        backward.push(t.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box(grads);
    }
    let rows = (images * per_image) as f64;
    let w = width as f64;
    // Per branch: (layers − 1) hidden layers, each a dW and a dX GEMM of rows × w × w.
    let backward_flops = 2.0 * (layers - 1) as f64 * 2.0 * 2.0 * rows * w * w;
    for (name, times) in [("forward", &mut forward), ("backward", &mut backward)] {
        let times = &mut times[5..];
        times.sort_by(f64::total_cmp);
        println!(
            "{name}: best {:.1} ms, median {:.1} ms",
            times[0],
            times[times.len() / 2]
        );
    }
    backward[5..].sort_by(f64::total_cmp);
    println!(
        "backward GEMMs: {:.1} GFLOP/s at the median",
        backward_flops / backward[backward.len() / 2 + 2] / 1e6
    );
}
