//! Expert scoring speed: baking both experts into 64³ grids, and the targets of K = 4096
//! rotations × 100 visible points for one image (what a training step needs per image).
//! Run with `cargo bench --bench experts`. The weights are untrained: speed does not depend on them.

use std::time::Instant;

use alignist::bundle::experts::{bake_experts, key_siren_config};
use alignist::cad::Shape;
use alignist::experts::SirenConfig;
use alignist::experts::energy::EnergyParams;
use alignist::experts::select::visible_points_at;
use alignist::so3::{haar_rotation, haar_rotations, to_row_major_f32};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn main() {
    let device = alignist::backend::device();
    let sdf = SirenConfig::new(3, 256, 4, 1).init(&device);
    let keys = key_siren_config().init(&device);
    let t = Instant::now();
    let baked = bake_experts(&sdf, &keys, 64, 1.05, EnergyParams::default(), &device);
    println!(
        "bake 64^3 SDF (3-256x4-1) and keys (3-256x2-12): {:.2} s",
        t.elapsed().as_secs_f64()
    );

    let mesh = Shape::Cube.mesh();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let r_gt = haar_rotation(&mut rng);
    let x0 = visible_points_at(&mesh, &r_gt, 0);
    let candidates: Vec<[f32; 9]> = haar_rotations(&mut rng, 4096)
        .iter()
        .map(to_row_major_f32)
        .collect();
    let mut times: Vec<f64> = (0..20)
        .map(|_| {
            let t = Instant::now();
            std::hint::black_box(baked.log_targets(&r_gt, &x0, &candidates));
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    println!(
        "targets of 4096 rotations x {} points: p50 {:.2} ms, min {:.2} ms ({} threads)",
        x0.len(),
        times[10],
        times[0],
        rayon::current_num_threads()
    );
}
