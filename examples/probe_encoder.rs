//! The tiny encoder's training forward and backward on the conv backend at the training bench's
//! shape (batch 16, 32 px; `--side N` for N px crops; `--deep` for `tiny_deep`) on burn and by hand (`net::encoder_grad`), with `--convs` each of
//! burn's convolutions alone first, with `--hand` the hand-written path alone: ms per pass, median of 20 after
//! 5 warm-up passes. For profiling (`perf record`) the encoder alone. `cargo run --release --example probe_encoder`
use std::time::Instant;

use alignist::net::{EncoderConfig, ResNetLayout, TrainingEncoder};
use burn::tensor::{Distribution, Tensor};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let side: usize = args
        .iter()
        .position(|a| a == "--side")
        .map(|i| {
            args.get(i + 1)
                .and_then(|v| v.parse().ok())
                .expect("--side N")
        })
        .unwrap_or(32);
    if std::env::args().any(|a| a == "--convs") {
        conv_shapes();
    }
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv).autodiff();
    device.seed(1);
    let layout = if std::env::args().any(|a| a == "--deep") {
        ResNetLayout::TinyDeep
    } else {
        ResNetLayout::Tiny
    };
    let encoder = EncoderConfig::new(layout).init(&device);
    let (mut forward, mut backward) = (Vec::new(), Vec::new());
    let burn_too = !std::env::args().any(|a| a == "--hand");
    for i in 0..if burn_too { 25 } else { 0 } {
        let x: Tensor<4> = Tensor::random([16, 3, side, side], Distribution::Default, &device);
        let t = Instant::now();
        let f = encoder.forward(x);
        let d = Tensor::<2>::random(f.dims(), Distribution::Default, &device);
        let s = (f * d).sum();
        let _ = s.clone().into_scalar::<f32>();
        let fwd = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let grads = s.backward();
        drop(grads);
        let bwd = t.elapsed().as_secs_f64() * 1e3;
        if i >= 5 {
            forward.push(fwd);
            backward.push(bwd);
        }
    }
    if burn_too {
        println!(
            "{layout:?} encoder, batch 16, {side} px, burn ({}): forward {:.1} ms, backward {:.1} ms (medians of 20)",
            alignist::backend::backend_for(alignist::backend::Workload::Conv),
            median(forward),
            median(backward)
        );
    }
    let (mut forward, mut backward) = (Vec::new(), Vec::new());
    let crops: Vec<Vec<u8>> = (0..16)
        .map(|i| {
            (0..side * side * 3)
                .map(|j| ((j * 7 + i * 13) % 251) as u8)
                .collect()
        })
        .collect();
    let crops: Vec<&[u8]> = crops.iter().map(|c| c.as_slice()).collect();
    let d = vec![0.01f32; 16 * layout.feature_dim()];
    for i in 0..25 {
        let t = Instant::now();
        let model = TrainingEncoder::of(&encoder, alignist::net::Kernels::default())
            .expect("the tiny layout");
        let pass = model.forward(&crops, side);
        let fwd = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let grads = model.backward(&pass, &d);
        let mut params = burn::optim::GradientsParams::new();
        grads.register(&model, &encoder, &mut params, &device);
        let bwd = t.elapsed().as_secs_f64() * 1e3;
        if i >= 5 {
            forward.push(fwd);
            backward.push(bwd);
        }
    }
    println!(
        "{layout:?} encoder, batch 16, {side} px, by hand (net::encoder_grad): forward {:.1} ms, backward {:.1} ms (medians of 20)",
        median(forward),
        median(backward)
    );
}

/// Each convolution of the tiny encoder at batch 16 on the conv backend: forward + backward ms
/// (median of 20) and the rate that makes of its FLOPs (forward, input gradient, weight
/// gradient: 3 × 2·B·C_in·C_out·k²·H'·W').
fn conv_shapes() {
    use burn::nn::PaddingConfig2d;
    use burn::nn::conv::Conv2dConfig;
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv).autodiff();
    // (c_in, c_out, k, stride, side)
    let shapes = [
        (3, 16, 3, 1, 32),
        (16, 16, 3, 1, 32),
        (16, 32, 3, 2, 32),
        (16, 32, 1, 2, 32),
        (32, 32, 3, 1, 16),
        (32, 64, 3, 2, 16),
        (64, 64, 3, 1, 8),
        (64, 128, 3, 2, 8),
        (128, 128, 3, 1, 4),
    ];
    let mut total = 0.0;
    for (c_in, c_out, k, stride, side) in shapes {
        let p = k / 2;
        let conv = Conv2dConfig::new([c_in, c_out], [k, k])
            .with_stride([stride, stride])
            .with_padding(PaddingConfig2d::Explicit(p, p, p, p))
            .with_bias(false)
            .init(&device);
        let x: Tensor<4> =
            Tensor::random([16, c_in, side, side], Distribution::Default, &device).require_grad();
        let mut times = Vec::new();
        for _ in 0..25 {
            let t = Instant::now();
            let y = conv.forward(x.clone());
            let grads = y.sum().backward();
            let dx = x.grad(&grads).expect("x is tracked");
            let dw = conv
                .weight
                .val()
                .grad(&grads)
                .expect("the weight is tracked");
            let _ = (dx.sum().into_scalar::<f32>(), dw.sum().into_scalar::<f32>());
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let ms = median(times[5..].to_vec());
        total += ms;
        let out = side / stride;
        let flops = 3.0 * 2.0 * (16 * c_in * c_out * k * k * out * out) as f64;
        println!(
            "conv {c_in:>3}→{c_out:<3} {k}×{k}/{stride} at {side:>2}²: forward + backward {ms:.2} ms, {:.1} GFLOP/s",
            flops / ms / 1e6
        );
    }
    println!("convolutions, forward + backward: {total:.1} ms");
}
