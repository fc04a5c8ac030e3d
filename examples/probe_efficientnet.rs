//! Reads the ImageNet EfficientNet-Lite0 weights (`scripts/fetch_pretrained.sh`), prints the
//! features of a fixed synthetic image (to compare with PyTorch on the same file), and times
//! training steps (forward, backward, Adam) of the encoder at a batch and crop size on the conv
//! backend: the cost a `--layout efficientnet-lite0` fit pays per step.
//!
//!     cargo run --release --example probe_efficientnet -- [WEIGHTS] [BATCH] [SIZE] [STEPS]
use alignist::net::EfficientNetLite0;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Distribution, Tensor, TensorData};
use std::path::Path;
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize, d: &str| args.get(i).cloned().unwrap_or_else(|| d.to_string());
    let weights = arg(0, "data/pretrained/efficientnet-lite0.pth");
    let batch: usize = arg(1, "16").parse()?;
    let size: usize = arg(2, "96").parse()?;
    let steps: usize = arg(3, "5").parse()?;
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv).autodiff();
    let t = Instant::now();
    let net = EfficientNetLite0::pretrained(Path::new(&weights), &device)?;
    println!("read {weights} in {:.2} s", t.elapsed().as_secs_f64());
    // A fixed image: channel c, row y, column x → ((c + 1)·(y·7 + x·3) mod 97) / 96.
    let s = 64;
    let pixels: Vec<f32> = (0..3 * s * s)
        .map(|i| {
            let (c, y, x) = (i / (s * s), i / s % s, i % s);
            ((c + 1) * (y * 7 + x * 3) % 97) as f32 / 96.0
        })
        .collect();
    let image = Tensor::<4>::from_data(TensorData::new(pixels, [1, 3, s, s]), &device);
    let features = net.valid().forward(image).mean_dim(3).mean_dim(2);
    let f: Vec<f32> = features.into_data().try_to_vec::<f32>()?;
    // As scripts/efficientnet_reference.py prints them from PyTorch.
    println!(
        "features of the fixed 64 px image (eval mode): at 848/566/949/384/27/268 {:?}, at 100/200/300 {:?}, sum {:.4}, zeros {}",
        [848, 566, 949, 384, 27, 268].map(|i| f[i]),
        [100, 200, 300].map(|i| f[i]),
        f.iter().sum::<f32>(),
        f.iter().filter(|v| **v == 0.0).count()
    );
    let mut net = net;
    let mut optim = AdamConfig::new().init();
    let mut times = Vec::new();
    for step in 0..steps {
        let x: Tensor<4> = Tensor::random([batch, 3, size, size], Distribution::Default, &device);
        let t = Instant::now();
        let loss = net
            .forward(x)
            .mean_dim(3)
            .mean_dim(2)
            .powf_scalar(2.0)
            .mean();
        let fwd = t.elapsed().as_secs_f64();
        let grads = GradientsParams::from_grads(loss.backward(), &net);
        net = optim.step(1e-4, net, grads);
        let all = t.elapsed().as_secs_f64();
        println!("step {step}: forward {fwd:.3} s, step {all:.3} s");
        if step > 0 {
            times.push(all);
        }
    }
    times.sort_by(f64::total_cmp);
    if let Some(m) = times.get(times.len() / 2) {
        println!("batch {batch} at {size} px: median training step {m:.3} s (after the first)");
    }
    Ok(())
}
