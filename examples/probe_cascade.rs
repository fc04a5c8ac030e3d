//! Whether a distilled head can pick the cells for its teacher (a cascade): the coarse levels of a
//! coarse-to-fine search scored by the narrow head, the finer ones by the teacher, on the
//! teacher's encoder features (a distilled head shares its teacher's frozen encoder). For each
//! cascade, and for the teacher alone ("narrow to level 0"), with and without a floor under the
//! halving keep: how often its top-1 lands in the cell (or a neighbour) of the teacher's exhaustive
//! level-5 argmax, and its p50 with the encoder. Then how far apart the two heads' level-3
//! argmaxes lie (on a symmetric shape each is one of many near-equal modes). The crops are the
//! bench's (clean renders, seed 99), so the figures sit beside the teacher's own search study.
//! `cargo run --release --example probe_cascade -- TEACHER STUDENT [IMAGES]`
use std::time::Instant;

use alignist::engine::search::{Keep, coarse_to_fine_many};
use alignist::engine::{Engine, EngineConfig, Model};
use alignist::net::Precision;
use alignist::so3::metrics::quantile;
use alignist::so3::{GridLevel, covering_radius, geodesic_angle, to_row_major_f32};

/// One cascade: start level 1, `keep` cells tapered ×0.5 a level (never fewer than `floor`),
/// levels up to `last_narrow` scored by the narrow head, the others by the teacher; every level
/// but the finest in [`COARSE`], the finest in f32.
#[derive(Debug, Clone, Copy)]
struct Cascade {
    keep: usize,
    floor: usize,
    last_narrow: u8,
}

const FINEST: u8 = 5;
const START: u8 = 1;
/// The arithmetic of the levels before the finest (the shipped model's calibrated choice here).
const COARSE: Precision = Precision::I8;

impl Cascade {
    /// The head and the arithmetic that score `level`.
    fn head_at<'a>(
        &self,
        level: u8,
        teacher: &'a Model,
        narrow: &'a Model,
    ) -> (&'a Model, Precision) {
        let head = if level <= self.last_narrow {
            narrow
        } else {
            teacher
        };
        (
            head,
            if level == FINEST {
                Precision::F32
            } else {
                COARSE
            },
        )
    }
}

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
        let (head, precision) = cascade.head_at(level, teacher, narrow);
        if level == START {
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
        Ok(head.score_rotations_many(features, &mats, precision))
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
            for last_narrow in [0, 2, 3, 4] {
                cascades.push(Cascade {
                    keep,
                    floor,
                    last_narrow,
                });
            }
        }
    }
    let grid = teacher.grid(FINEST).expect("grid");
    let neighbour = 2.0 * covering_radius(FINEST);
    let mut agree = vec![0usize; cascades.len()];
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); cascades.len()];
    let level3 = teacher.grid(3).expect("grid");
    let mut apart_deg = Vec::new();
    for (n, crop) in crops.iter().enumerate() {
        let features = teacher.features(&[crop])?;
        let same = narrow.features(&[crop])?;
        let drift = features[0]
            .iter()
            .zip(&same[0])
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        anyhow::ensure!(drift < 1e-4, "the two bundles' encoders differ ({drift})");
        let argmax = |logits: Vec<f32>| {
            logits
                .iter()
                .enumerate()
                .fold((0, f32::MIN), |b, (i, &l)| if l > b.1 { (i, l) } else { b })
                .0 as u64
        };
        apart_deg.push(
            geodesic_angle(
                &level3.rotation(argmax(teacher.logits_at(&features[0], 3)?)),
                &level3.rotation(argmax(narrow.logits_at(&features[0], 3)?)),
            )
            .to_degrees(),
        );
        let best = grid.rotation(argmax(teacher.logits_at(&features[0], FINEST)?));
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
    println!(
        "cascade (start 1, keep ×0.5/level, coarse {COARSE}, finest f32)   agreement  p50 (encoder incl.)"
    );
    for (c, cascade) in cascades.iter().enumerate() {
        println!(
            "keep {:4} (at least {:3}), narrow head to level {} (0: teacher alone)   {:5.1} %   {:6.1} ms",
            cascade.keep,
            cascade.floor,
            cascade.last_narrow,
            100.0 * agree[c] as f64 / crops.len() as f64,
            quantile(&times[c], 0.5)
        );
    }
    let far = apart_deg.iter().filter(|&&a| a > 90.0).count();
    println!(
        "the two heads' level-3 argmaxes: median {:.1}° apart, more than 90° apart on {far} of {} crops",
        quantile(&apart_deg, 0.5),
        apart_deg.len()
    );
    Ok(())
}
