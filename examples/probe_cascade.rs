//! Whether a distilled head can pick the cells for its teacher (a cascade): the coarse levels of a
//! coarse-to-fine search scored by the narrow head, the finer ones by the teacher, on the
//! teacher's encoder features (a distilled head shares its teacher's frozen encoder). For each
//! cascade, and for the teacher alone ("narrow to level 0"), with and without a floor under the
//! halving keep: how often its top-1 lands in the cell (or a neighbour) of the teacher's exhaustive
//! level-5 argmax, and its p50 with the encoder. The crops are the bench's (clean renders,
//! seed 99), so the figures sit beside the teacher's own search study.
//! `cargo run --release --example probe_cascade -- TEACHER STUDENT [IMAGES]`
use std::time::Instant;

use alignist::engine::search::{Keep, coarse_to_fine_many};
use alignist::engine::{Engine, EngineConfig, Model};
use alignist::net::Precision;
use alignist::so3::{GridLevel, covering_radius, geodesic_angle, to_row_major_f32};

/// One cascade: start level 1, `keep` cells tapered ×0.5 a level, levels up to `last_narrow`
/// scored by the narrow head in `narrow`, the teacher's levels below the finest in `teacher`
/// (the finest always in f32).
#[derive(Debug, Clone, Copy)]
struct Cascade {
    keep: usize,
    /// The fewest cells kept at any level.
    floor: usize,
    last_narrow: u8,
    narrow: Precision,
    teacher: Precision,
}

const FINEST: u8 = 5;
const START: u8 = 1;

fn run(
    cascade: &Cascade,
    teacher: &Model,
    narrow: &Model,
    features: &[Vec<f32>],
) -> anyhow::Result<u64> {
    let grids: Vec<&GridLevel> = (START..=FINEST)
        .map(|l| teacher.grid(l).expect("grid"))
        .collect();
    let keep = Keep {
        max: cascade.keep,
        min: cascade.floor,
        mass: None,
        taper: 0.5,
    };
    let results = coarse_to_fine_many(&grids, keep, 1, |grid, cells| {
        let level = grid.level();
        if level == START {
            let head = if level <= cascade.last_narrow {
                narrow
            } else {
                teacher
            };
            let precision = if level <= cascade.last_narrow {
                cascade.narrow
            } else {
                cascade.teacher
            };
            return head
                .logits_in(precision, &features[0], level)
                .map(|l| vec![l]);
        }
        let mats: Vec<Vec<[f32; 9]>> = cells
            .iter()
            .map(|c| {
                c.iter()
                    .map(|&c| to_row_major_f32(&grid.rotation(c)))
                    .collect()
            })
            .collect();
        Ok(if level <= cascade.last_narrow {
            narrow.score_rotations_many(features, &mats, cascade.narrow)
        } else if level < FINEST {
            teacher.score_rotations_many(features, &mats, cascade.teacher)
        } else {
            teacher.score_rotations_many(features, &mats, Precision::F32)
        })
    })?;
    Ok(results[0].cells[0].cell)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        args.len() >= 3,
        "usage: probe_cascade TEACHER STUDENT [IMAGES]"
    );
    let images: usize = args.get(3).map_or(Ok(50), |s| s.parse())?;
    let bundle = alignist::bundle::model::ModelBundle::load(std::path::Path::new(&args[1]))?;
    let renders = alignist::train::data::BundleRenders::of(&bundle, 4);
    let per_object = images.div_ceil(renders.names.len());
    let crops: Vec<Vec<u8>> = renders
        .eval_images(bundle.manifest.network.image_size, per_object, 99)
        .into_iter()
        .map(|im| im.rgb)
        .collect();
    let teacher = Engine::load_model(std::path::Path::new(&args[1]), EngineConfig::default())?;
    let narrow = Engine::load_model(std::path::Path::new(&args[2]), EngineConfig::default())?;
    let mut cascades = Vec::new();
    for keep in [128, 192, 256, 384, 512] {
        for floor in [2, 64, 96] {
            for last_narrow in [0, 2] {
                cascades.push(Cascade {
                    keep,
                    floor,
                    last_narrow,
                    narrow: Precision::I8,
                    teacher: Precision::I8,
                });
            }
        }
    }
    let grid = teacher.grid(FINEST).expect("grid");
    let neighbour = 2.0 * covering_radius(FINEST);
    let mut agree = vec![0usize; cascades.len()];
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); cascades.len()];
    for (n, crop) in crops.iter().enumerate() {
        let features = teacher.features(&[crop])?;
        let same = narrow.features(&[crop])?;
        let drift = features[0]
            .iter()
            .zip(&same[0])
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        anyhow::ensure!(drift < 1e-4, "the two bundles' encoders differ ({drift})");
        let logits = teacher.logits_at(&features[0], FINEST)?;
        let best = logits
            .iter()
            .enumerate()
            .fold((0, f32::MIN), |b, (i, &l)| if l > b.1 { (i, l) } else { b })
            .0;
        let best = grid.rotation(best as u64);
        for (c, cascade) in cascades.iter().enumerate() {
            let t = Instant::now();
            let f = teacher.features(&[crop])?;
            let top = run(cascade, &teacher, &narrow, &f)?;
            times[c].push(t.elapsed().as_secs_f64() * 1e3);
            if geodesic_angle(&grid.rotation(top), &best) <= neighbour {
                agree[c] += 1;
            }
        }
        eprint!("\r{}/{} images", n + 1, crops.len());
    }
    eprintln!();
    println!("cascade (start 1, keep ×0.5/level)          agreement  p50 (encoder incl.)");
    for (c, cascade) in cascades.iter().enumerate() {
        times[c].sort_by(f64::total_cmp);
        println!(
            "keep {:4} (at least {:3}), narrow to level {} in {:4} (0: none), teacher {:4} then f32   {:5.1} %   {:6.1} ms",
            cascade.keep,
            cascade.floor,
            cascade.last_narrow,
            cascade.narrow.to_string(),
            cascade.teacher.to_string(),
            100.0 * agree[c] as f64 / crops.len() as f64,
            times[c][times[c].len() / 2]
        );
    }
    Ok(())
}
