//! How sharp and how right the experts' targets are, as a distribution over the whole grid: the
//! distribution the network is trained towards (`p ∝ a^SDF · a^SE`, paper Eq. 3–4), for
//! Haar-random true rotations and the points visible at each. Prints, per expert set, its LL
//! (`log(p_cell · N)` of the true rotation's cell, DESIGN.md §2: uniform 0, all the mass in that
//! cell `log N`), the geodesic error of
//! its argmax (AR@30: the share under 30°, with no symmetry taken into account: for asymmetric
//! parts), and the mass within 30° of the true rotation.
//! `cargo run --release --example probe_target_sharpness EXPERTS_DIR… [-- LEVEL ROTATIONS]`
use alignist::bundle::experts::ExpertSet;
use alignist::experts::select::visible_points_at;
use alignist::so3::{GridLevel, geodesic_angle, haar_rotation};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (dirs, rest) = match args.iter().position(|a| a == "--") {
        Some(i) => (&args[..i], &args[i + 1..]),
        None => (&args[..], &[][..]),
    };
    let level: u8 = rest.first().map_or(Ok(3), |s| s.parse())?;
    let n: u64 = rest.get(1).map_or(Ok(20), |s| s.parse())?;
    let grid = GridLevel::new(level)?;
    let mats = grid.matrices_f32();
    let log_n = (grid.len() as f64).ln();
    println!(
        "level {level} ({} cells): LL of all the mass in the true cell {log_n:.2}, uniform 0",
        grid.len()
    );
    for dir in dirs {
        let set = ExpertSet::load(std::path::Path::new(dir))?;
        let baked = set.bake();
        let (mut ll, mut hits, mut near_mass, mut errors) = (0.0, 0, 0.0, Vec::new());
        for seed in 0..n {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let r_gt = haar_rotation(&mut rng);
            let x0 = visible_points_at(&set.mesh, &r_gt, seed);
            let t = baked.log_targets(&r_gt, &x0, &mats);
            let log_p: Vec<f64> = t
                .log_a_sdf
                .iter()
                .zip(&t.log_a_se)
                .map(|(a, b)| (a + b) as f64)
                .collect();
            let max = log_p.iter().copied().fold(f64::MIN, f64::max);
            let lse = max + log_p.iter().map(|l| (l - max).exp()).sum::<f64>().ln();
            ll += log_p[grid.cell_of(&r_gt) as usize] - lse + log_n;
            let best = (0..log_p.len()).max_by(|&a, &b| log_p[a].total_cmp(&log_p[b]));
            let error =
                geodesic_angle(&grid.rotation(best.unwrap_or(0) as u64), &r_gt).to_degrees();
            hits += usize::from(error < 30.0);
            errors.push(error);
            near_mass += log_p
                .iter()
                .enumerate()
                .filter(|(c, _)| {
                    geodesic_angle(&grid.rotation(*c as u64), &r_gt).to_degrees() < 30.0
                })
                .map(|(_, l)| (l - lse).exp())
                .sum::<f64>();
        }
        errors.sort_by(f64::total_cmp);
        println!(
            "{dir}: LL {:.2}, argmax AR@30 {:.2}, median argmax error {:.1}°, mass within 30° {:.2} ({n} rotations)",
            ll / n as f64,
            hits as f64 / n as f64,
            errors[errors.len() / 2],
            near_mass / n as f64
        );
    }
    Ok(())
}
