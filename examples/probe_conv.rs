//! Times the query U-Net and the key SIREN, forward and backward, on the conv backend.
use alignist::experts::feature::QueryNetConfig;
use burn::tensor::{Distribution, Tensor};
use std::time::Instant;

fn main() {
    // Set ALIGNIST_BACKEND=ndarray or =flex to compare the backends on this workload.
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv).autodiff();
    println!(
        "backend {}",
        alignist::backend::backend_for(alignist::backend::Workload::Conv)
    );
    let net = QueryNetConfig::new().init(&device);
    for size in [32usize, 64] {
        let x: Tensor<4> = Tensor::random([8, 3, size, size], Distribution::Default, &device);
        let t = Instant::now();
        let y = net.forward(x.clone());
        let s = y.clone().sum();
        let _ = s.clone().into_scalar::<f32>();
        let fwd = t.elapsed();
        let g = s.backward();
        drop(g);
        println!(
            "size {size}: forward {:?}, forward+backward {:?}",
            fwd,
            t.elapsed()
        );
    }
    let keys = alignist::experts::SirenConfig::new(3, 256, 2, 12).init(&device);
    let p: Tensor<2> = Tensor::random([1536, 3], Distribution::Default, &device);
    let t = Instant::now();
    let k = keys.forward(p).sum();
    let _ = k.backward();
    println!("keys 1536 pts fwd+bwd {:?}", t.elapsed());
}
