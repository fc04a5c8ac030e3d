//! Probe: which single rotation of a distribution is right most often, on `eval`'s crops.
//! `cargo run --release --example probe_points MODEL_DIR [IMAGES] [SET]` (SET: clean, train,
//! held-out (default), boxes; the crops and seeds of `alignist-train eval --fresh --realistic`)
//! scores the full level-3 distribution of each crop and prints the AR@30 and median error of
//! several point estimates: the argmax (the sharpest cell), the first mode (as `eval`), and the
//! centre of the densest ball of radius r (the cell whose r-neighbourhood holds the most mass:
//! for r = 30° the rotation most probably within 30° of the truth, the Bayes choice for AR@30).
use alignist::bundle::model::ModelBundle;
use alignist::data::realism::{Realism, Split};
use alignist::engine::{Engine, EngineConfig};
use alignist::so3::metrics::{accuracy_and_median, error_to_nearest_deg, first_mode};

/// Candidate centres (the most probable cells) and the cells whose mass is summed.
const CANDIDATES: usize = 512;
const POOL: usize = 4096;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dir = std::path::Path::new(&args[1]);
    let n: usize = args.get(2).map_or(100, |a| a.parse().unwrap());
    let set = args.get(3).map_or("held-out", String::as_str);
    let bundle = ModelBundle::load(dir).unwrap();
    let renders = alignist::train::data::BundleRenders::of(&bundle, 2);
    let model = Engine::load_model(dir, EngineConfig::default()).unwrap();
    let size = model.input_size();
    let seed = alignist::train::data::EVAL_SEED;
    let images = match set {
        "clean" => renders.eval_images(size, n, seed),
        "held-out" => renders.eval_realistic_images(size, n, Split::HeldOut),
        "boxes" => renders.realistic_eval_images(size, n, seed + 1, Realism::held_out_boxes(0.08)),
        "train" => renders.eval_realistic_images(size, n, Split::Train),
        other => panic!("set {other}: clean, train, held-out or boxes"),
    };
    let grid = model.grid(3).unwrap().clone();
    let centres = grid.quaternions();
    let radii = [10.0f64, 15.0, 20.0, 30.0, 45.0];
    let mut errors: Vec<Vec<f64>> = vec![Vec::new(); 2 + radii.len()];
    for im in &images {
        let f = model.features(&[&im.rgb]).unwrap().swap_remove(0);
        let d = model.distribution(&f, 3, None).unwrap();
        let p: Vec<f64> = d.probability.iter().map(|&v| v as f64).collect();
        let mut order: Vec<usize> = (0..p.len()).collect();
        order.sort_unstable_by(|&a, &b| p[b].total_cmp(&p[a]));
        let err_of_cell =
            |c: usize| error_to_nearest_deg(&grid.rotation(c as u64), &im.equivalents);
        errors[0].push(err_of_cell(order[0]));
        let mode = first_mode(&grid, &p).unwrap();
        let r = alignist::so3::from_quaternion(mode.quaternion).unwrap();
        errors[1].push(error_to_nearest_deg(&r, &im.equivalents));
        for (k, radius) in radii.iter().enumerate() {
            // |q·q'| ≥ cos(r/2): within r of each other.
            let min_dot = (radius.to_radians() / 2.0).cos();
            let best = order[..CANDIDATES]
                .iter()
                .map(|&c| {
                    let q = centres[c];
                    let mass: f64 = order[..POOL]
                        .iter()
                        .filter(|&&o| {
                            let d = (0..4).map(|i| q[i] * centres[o][i]).sum::<f64>();
                            d.abs() >= min_dot
                        })
                        .map(|&o| p[o])
                        .sum();
                    (c, mass)
                })
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            errors[2 + k].push(err_of_cell(best.0));
        }
    }
    println!(
        "{} crops ({set}) of {}: AR@30 and median error of each point estimate",
        images.len(),
        dir.display()
    );
    let mut names = vec!["argmax".to_string(), "first mode (15°)".to_string()];
    names.extend(radii.iter().map(|r| format!("densest ball, r {r}°")));
    for (name, e) in names.iter().zip(&errors) {
        let (acc, median) = accuracy_and_median(e, &[30.0]);
        println!("  {name:24} AR@30 {:.3}  median {median:6.1}°", acc[0].1);
    }
}
