//! Probe: how the expert targets look on the K rotations the trainer samples for one image.
//! `cargo run --release --example probe_targets EXPERTS_DIR` prints, for mode-focused sampling
//! from the set's mode table, the quantiles of log a^SDF and log a^SE (relative to the ground
//! truth) on the focused samples, and the fraction of them whose combined target exceeds 0.1.
use alignist::bundle::experts::ExpertSet;
use alignist::experts::select::visible_points_at;
use alignist::so3::{haar_rotation, to_row_major_f32};
use alignist::train::{ModeSampler, SamplingStrategy, sample_rotations};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn main() {
    let Some(dir) = std::env::args().nth(1) else {
        eprintln!("usage: probe_targets EXPERTS_DIR");
        std::process::exit(2);
    };
    let set = ExpertSet::load(std::path::Path::new(&dir)).unwrap();
    let baked = set.bake();
    let table = set.mode_table(&baked).unwrap();
    let sampler = ModeSampler::new(&table, 0.0).unwrap();
    let strategy = SamplingStrategy::mode_focused(256);
    let focused = 192;
    for seed in 0..3u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let r_gt = haar_rotation(&mut rng);
        let x0 = visible_points_at(&set.mesh, &r_gt, seed);
        let samples = sample_rotations(&strategy, 256, &r_gt, Some(&sampler), &mut rng);
        let mats: Vec<[f32; 9]> = samples.iter().map(to_row_major_f32).collect();
        let t = baked.log_targets(&r_gt, &x0, &mats);
        let rel = |v: &[f32]| -> Vec<f32> { v[1..=focused].iter().map(|x| x - v[0]).collect() };
        let q = |v: &[f32]| {
            let mut v = v.to_vec();
            v.sort_by(f32::total_cmp);
            [0.1, 0.5, 0.9, 1.0].map(|p| v[((v.len() - 1) as f32 * p) as usize])
        };
        let (sdf, se) = (rel(&t.log_a_sdf), rel(&t.log_a_se));
        let above = sdf
            .iter()
            .zip(&se)
            .filter(|(a, b)| (*a + *b).exp() > 0.1)
            .count();
        println!(
            "seed {seed}: {} table cells; focused log a_sdf q10/50/90/max {:?}, log a_se {:?}; \
             {above}/{focused} focused samples with a_sdf·a_se > 0.1 (relative to the GT)",
            table.cells.len(),
            q(&sdf),
            q(&se),
        );
    }
}
