//! Where a coarse-to-fine search's time goes: runs one search (start level, keep, coarse
//! precision, keep taper from the arguments) to level 5 on held-out renders of a bundle,
//! repeatedly, prints its p50, then times its parts alone with the same numbers of rotations: the
//! encoder, the start level in full, each refined level (from its precomputed projections up to
//! the highest full level, above it from encoded rotations), and the rest (cell rotations,
//! softmax, selection, modes) as the difference.
//! `cargo run --release --example probe_search [BUNDLE] [START] [KEEP] [f32|bf16|f16|i8] [REPEATS]
//! [TAPER] [KEEP_MASS|-] [RESCORE_FINEST: true|false] [SHAPE_ONLY_TO|-] [FULL_LEVEL]` (with a
//! keep by mass, the parts are timed at the most cells kept; `-`: no keep by mass, both branches
//! at every level; FULL_LEVEL: also time the same search, calls alternating, on the model loaded
//! with this highest full level, whose projections are precomputed (FULL_LEVEL = START scores
//! every refined level from encodings)).
use std::time::Instant;

use alignist::engine::{Engine, EngineConfig, Model, PredictOptions, RESCORED_CELLS, SearchParams};
use alignist::net::Precision;
use alignist::so3::to_row_major_f32;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, default: &str| args.get(i).cloned().unwrap_or_else(|| default.into());
    let path = std::path::PathBuf::from(arg(1, "models/symsol1"));
    let search = SearchParams {
        start_level: arg(2, "2").parse()?,
        keep: arg(3, "1024").parse()?,
        keep_mass: args
            .get(7)
            .filter(|m| *m != "-")
            .map(|m| m.parse())
            .transpose()?,
        keep_taper: arg(6, "0.5").parse()?,
        coarse_precision: arg(4, "bf16")
            .parse::<Precision>()
            .map_err(anyhow::Error::msg)?,
        rescore_finest: arg(8, "false").parse()?,
        shape_only_to: args
            .get(9)
            .filter(|l| *l != "-")
            .map(|l| l.parse())
            .transpose()?,
    };
    let repeats: usize = arg(5, "20").parse()?;
    let bundle = alignist::bundle::model::ModelBundle::load(&path)?;
    let images: Vec<Vec<u8>> = alignist::train::data::BundleRenders::of(&bundle, 2)
        .eval_images(bundle.manifest.network.image_size, 2, 7)
        .into_iter()
        .map(|im| im.rgb)
        .collect();
    let model = Engine::load_model(&path, EngineConfig::default())?;
    // With FULL_LEVEL, a second model with that highest full level, its calls alternating with
    // the first's (a paired comparison: both meet the same moments of the machine).
    let other = match args.get(10) {
        Some(full) => {
            let mut config = EngineConfig {
                max_full_level: full.parse()?,
                ..EngineConfig::default()
            };
            // The engine's own search must start from a full level too.
            config.search.start_level = config.search.start_level.min(config.max_full_level);
            Some((config.max_full_level, Engine::load_model(&path, config)?))
        }
        None => None,
    };
    let options = PredictOptions {
        top_k: 10,
        level: Some(FINEST),
        mode_angle_deg: None,
        ..Default::default()
    };
    let call = |model: &Model, im: &[u8]| {
        let t = Instant::now();
        let f = model.features(&[im]).expect("crops of the input side");
        model
            .predict_searching(&f, &options, &search, &[None])
            .expect("search");
        t.elapsed().as_secs_f64() * 1e3
    };
    let (mut times, mut others) = (Vec::new(), Vec::new());
    for im in (0..repeats).flat_map(|_| &images) {
        times.push(call(&model, im));
        if let Some((_, other)) = &other {
            others.push(call(other, im));
        }
    }
    let total = median(times);
    println!("{search:?}, top-10 to level {FINEST}: p50 {total:.1} ms");
    if let Some((full, _)) = &other {
        println!(
            "  the same search with the highest full level {full} (calls alternating): p50 {:.1} ms",
            median(others)
        );
    }
    let parts = time_parts(&model, &search, &images[0], repeats * images.len());
    println!(
        "  the rest (cell rotations, softmax, selection, modes): {:.1} ms",
        total - parts
    );
    Ok(())
}

/// The finest level of the searches.
const FINEST: u8 = 5;

/// Times the search's parts alone, `runs` times each (median): the encoder, the start level in
/// full, each refined level with the search's numbers of rotations; returns their sum (ms).
fn time_parts(model: &Model, search: &SearchParams, crop: &[u8], runs: usize) -> f64 {
    let timed = |f: &mut dyn FnMut()| {
        median(
            (0..runs)
                .map(|_| {
                    let t = Instant::now();
                    f();
                    t.elapsed().as_secs_f64() * 1e3
                })
                .collect(),
        )
    };
    let features = model.features(&[crop]).expect("crops of the input side");
    let encoder = timed(&mut || {
        model.features(&[crop]).expect("crops of the input side");
    });
    println!("  encoder: {encoder:.1} ms");
    let start_precision = search.precision_at(search.start_level, search.start_level, FINEST);
    let start_branches = search.branches_at(search.start_level, FINEST);
    let start = timed(&mut || {
        model
            .logits_by(
                (start_precision, start_branches),
                &features[0],
                search.start_level,
            )
            .expect("start level");
    });
    let start_len = model.grid(search.start_level).map_or(0, |g| g.len());
    println!(
        "  level {} in full ({start_len} rotations, {start_precision}, {start_branches:?}): {start:.1} ms",
        search.start_level
    );
    let mut parts = encoder + start;
    for (i, level) in (search.start_level + 1..=FINEST).enumerate() {
        let keep = (search.keep as f64 * search.keep_taper.powi(i as i32)).round() as usize;
        let grid = model.grid(level).expect("grid");
        let cells: Vec<u64> = (0..8 * keep as u64)
            .map(|c| c * 97 % grid.len() as u64)
            .collect();
        let precision = search.precision_at(level, search.start_level, FINEST);
        let branches = search.branches_at(level, FINEST);
        let (t, source) = match model.projected(level) {
            Some(projected) => (
                timed(&mut || {
                    projected.log_weights_of_cells_by(precision, branches, &features[0], &cells);
                }),
                "projections gathered",
            ),
            None => {
                let rotations: Vec<[f32; 9]> = cells
                    .iter()
                    .map(|&c| to_row_major_f32(&grid.rotation(c)))
                    .collect();
                let t = timed(&mut || {
                    model.score_rotations_by(
                        &features,
                        std::slice::from_ref(&rotations),
                        precision,
                        branches,
                    );
                });
                (t, "encodings included")
            }
        };
        println!(
            "  level {level} ({} rotations, {precision}, {branches:?}, {source}): {t:.1} ms",
            cells.len()
        );
        parts += t;
    }
    if search.rescores_to(search.start_level, FINEST) {
        let grid = model.grid(FINEST).expect("grid");
        let rotations: Vec<[f32; 9]> = (0..RESCORED_CELLS.max(10) as u64)
            .map(|c| to_row_major_f32(&grid.rotation(c * 97 % grid.len() as u64)))
            .collect();
        let t = timed(&mut || {
            model.score_rotations_many(&features, std::slice::from_ref(&rotations), Precision::F32);
        });
        println!(
            "  level {FINEST} rescored ({} rotations, f32): {t:.1} ms",
            rotations.len()
        );
        parts += t;
    }
    parts
}
