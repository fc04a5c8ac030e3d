//! Probe: how the expert targets look on the K rotations the trainer samples for one image.
//! `cargo run --release --example probe_targets EXPERTS_DIR [LEVEL] [FINE_LEVEL]` prints, for
//! mode-focused sampling searched from LEVEL down to FINE_LEVEL, the quantiles of log a^SDF and log a^SE and the fraction
//! of samples whose combined target exceeds 0.1.
use alignist::bundle::experts::ExpertSet;
use alignist::experts::select::visible_points_at;
use alignist::so3::{haar_rotation, to_row_major_f32};
use alignist::train::{ModeSearch, SamplingStrategy, sample_rotations};
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
    let fine: u8 = std::env::args()
        .nth(3)
        .and_then(|s| s.parse().ok())
        .unwrap_or(4);
    let strategy = SamplingStrategy::ModeFocused {
        focused: 192,
        level,
        fine_level: fine,
        keep: 256,
    };
    let search = ModeSearch::new(level, fine, 256).unwrap();
    for seed in 0..3u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let r_gt = haar_rotation(&mut rng);
        let x0 = visible_points_at(&set.mesh, &r_gt, seed);
        let t0 = std::time::Instant::now();
        let modes = search.expert_modes(|r| {
            let t = baked.log_targets(&r_gt, &x0, r);
            t.log_a_sdf
                .iter()
                .zip(&t.log_a_se)
                .map(|(a, b)| a + b)
                .collect()
        });
        let search_ms = t0.elapsed().as_secs_f64() * 1e3;
        let samples = sample_rotations(
            &strategy,
            256,
            &r_gt,
            Some((search.fine_grid(), &modes)),
            &mut rng,
        );
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
            "level {level}→{fine} seed {seed} (search {search_ms:.0} ms): focused log a_sdf q10/50/90/max {:?}, log a_se {:?}; {above}/192 focused samples with a_sdf·a_se > 0.1; GT: {:.2} {:.2}",
            q(&t.log_a_sdf[1..193]),
            q(&t.log_a_se[1..193]),
            t.log_a_sdf[0],
            t.log_a_se[0]
        );
    }
}
