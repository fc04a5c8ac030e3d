//! Probe: how the expert targets look on the K rotations the trainer samples for one image.
//! `cargo run --release --example probe_targets EXPERTS_DIR [LEVEL]` prints, for mode-focused
//! sampling at the given coarse level, the quantiles of log a^SDF and log a^SE and the fraction
//! of samples whose combined target exceeds 0.1.
use alignist::bundle::experts::ExpertSet;
use alignist::experts::select::visible_points_at;
use alignist::so3::{GridLevel, haar_rotation, to_row_major_f32};
use alignist::train::{SamplingStrategy, sample_rotations};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn main() {
    let dir = std::env::args().nth(1).expect("EXPERTS_DIR");
    let level: u8 = std::env::args()
        .nth(2)
        .and_then(|s| s.parse().ok())
        .unwrap_or(2);
    let set = ExpertSet::load(std::path::Path::new(&dir)).unwrap();
    let baked = set.bake();
    let grid = GridLevel::new(level).unwrap();
    let cells = grid.matrices_f32();
    for seed in 0..3u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let r_gt = haar_rotation(&mut rng);
        let x0 = visible_points_at(&set.mesh, &r_gt, seed);
        let coarse = baked.log_targets(&r_gt, &x0, &cells);
        let combined: Vec<f32> = coarse
            .log_a_sdf
            .iter()
            .zip(&coarse.log_a_se)
            .map(|(a, b)| a + b)
            .collect();
        let strategy = SamplingStrategy::ModeFocused {
            focused: 192,
            level,
        };
        let samples = sample_rotations(&strategy, 256, &r_gt, Some((&grid, &combined)), &mut rng);
        let mats: Vec<[f32; 9]> = samples.iter().map(to_row_major_f32).collect();
        let t = baked.log_targets(&r_gt, &x0, &mats);
        let q = |v: &[f32]| {
            let mut v = v.to_vec();
            v.sort_by(f32::total_cmp);
            [0.1, 0.5, 0.9, 1.0].map(|p| v[((v.len() - 1) as f32 * p) as usize])
        };
        let focused_combined: Vec<f32> = t.log_a_sdf[1..193]
            .iter()
            .zip(&t.log_a_se[1..193])
            .map(|(a, b)| a + b)
            .collect();
        let above = focused_combined.iter().filter(|&&c| c.exp() > 0.1).count();
        println!(
            "level {level} seed {seed}: focused log a_sdf q10/50/90/max {:?}, log a_se {:?}; {above}/192 focused samples with a_sdf·a_se > 0.1; GT: {:.2} {:.2}",
            q(&t.log_a_sdf[1..193]),
            q(&t.log_a_se[1..193]),
            t.log_a_sdf[0],
            t.log_a_se[0]
        );
    }
}
