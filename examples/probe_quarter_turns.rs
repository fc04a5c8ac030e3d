//! Test-time quarter turns: is the network's answer on a crop better when it also looks at the
//! crop turned by a quarter, a half and three quarters of a turn? Turning a square crop about its
//! centre by k quarter turns (exact: no resampling) shows the object at `Q^k · R`, `Q` a quarter
//! turn about the camera's line of sight (z); so the crop's log-density at `R` can be read from
//! each turned crop at `Q^k · R`, and the views combined: their sum (a product of the densities)
//! or their log-mean-exp (a mixture), or the surest view taken alone (the one whose most probable
//! cell is the most probable), or a vote among the views' answers. For every crop of a set (`eval --fresh`'s crops: clean, or
//! realistic `train` / `held-out`), this scores a full grid level in each view with the engine's
//! f32 head at the turned rotations, and prints the project's metrics (`so3::metrics::image_metrics`: AR@30 of
//! the argmax and of the first mode, LL, median error) of: the crop alone, each turned view alone,
//! the half-turn pair, and all four, against the ceiling and chance. The sign of `Q` is found
//! first, from the crops: the quarter-turned view alone scored at `Q · R` for both signs.
//! `cargo run --release --example probe_quarter_turns BUNDLE [IMAGES_PER_PART] [LEVEL] [clean|train|held-out]`
use std::f64::consts::FRAC_PI_2;

use alignist::bundle::model::ModelBundle;
use alignist::data::realism::Split;
use alignist::engine::search::log_sum_exp;
use alignist::engine::{Engine, EngineConfig, Model};
use alignist::net::Precision;
use alignist::so3::metrics::{ImageMetrics, image_metrics};
use alignist::so3::{GridLevel, to_row_major_f32};
use alignist::train::data::BundleRenders;
use alignist::train::eval::EvalImage;
use nalgebra::{Rotation3, Vector3};

/// `rgb` (`size`² RGB8) turned a quarter counter-clockwise as displayed, `k` times.
fn quarter_turns(rgb: &[u8], size: usize, k: usize) -> Vec<u8> {
    let mut out = rgb.to_vec();
    for _ in 0..k % 4 {
        let src = out.clone();
        for y in 0..size {
            for x in 0..size {
                // (x, y) → (y, size − 1 − x): the top-right corner goes to the top left.
                let (to, from) = (((size - 1 - x) * size + y) * 3, (y * size + x) * 3);
                out[to..to + 3].copy_from_slice(&src[from..from + 3]);
            }
        }
    }
    out
}

/// How a combination reads its views.
#[derive(Clone, Copy, PartialEq)]
enum Rule {
    /// The sum of their log-probabilities: a product of the densities.
    Product,
    /// Their log-mean-exp: a mixture.
    Mixture,
    /// The one view whose most probable cell is the most probable.
    Surest,
    /// The one view whose most probable cell the most other views' most probable cells lie
    /// within 30° of (a vote; ties to the earlier view). Angles without the part's symmetries:
    /// for parts without one.
    Vote,
}

/// One way of combining views: its name, the views it takes, and how.
struct Combination(&'static str, &'static [usize], Rule);

const COMBINATIONS: [Combination; 11] = [
    Combination("the crop alone", &[0], Rule::Product),
    Combination("turned 1/4 alone", &[1], Rule::Product),
    Combination("turned 1/2 alone", &[2], Rule::Product),
    Combination("turned 3/4 alone", &[3], Rule::Product),
    Combination("0 + 1/2, product", &[0, 2], Rule::Product),
    Combination("all four, product", &[0, 1, 2, 3], Rule::Product),
    Combination("all four, mixture", &[0, 1, 2, 3], Rule::Mixture),
    Combination("0 or 1/2, the surer", &[0, 2], Rule::Surest),
    Combination("all four, the surest", &[0, 1, 2, 3], Rule::Surest),
    Combination("all four, a vote", &[0, 1, 2, 3], Rule::Vote),
    Combination("0, 1/2, 1/4: a vote", &[0, 2, 1], Rule::Vote),
];

impl Combination {
    /// The combined log-weights of every cell from each view's log-probabilities.
    fn of(&self, views: &[Vec<f64>], cells: &[Rotation3<f64>]) -> Vec<f32> {
        if self.2 == Rule::Vote {
            let best = |k: usize| {
                let v = &views[k];
                let i = (0..v.len())
                    .max_by(|&a, &b| v[a].total_cmp(&v[b]))
                    .expect("a grid has cells");
                cells[i]
            };
            let answers: Vec<Rotation3<f64>> = self.1.iter().map(|&k| best(k)).collect();
            let support = |a: &Rotation3<f64>| {
                answers
                    .iter()
                    .filter(|b| (a.inverse() * *b).angle().to_degrees() <= 30.0)
                    .count()
            };
            // The first of the most supported (max_by keeps the last of equals, so reversed).
            let chosen = (0..answers.len())
                .rev()
                .max_by_key(|&i| support(&answers[i]))
                .expect("a combination has views");
            return views[self.1[chosen]].iter().map(|&v| v as f32).collect();
        }
        if self.2 == Rule::Surest {
            let peak = |k: usize| views[k].iter().copied().fold(f64::MIN, f64::max);
            let surest = self
                .1
                .iter()
                .copied()
                .max_by(|&a, &b| peak(a).total_cmp(&peak(b)))
                .expect("a combination has views");
            return views[surest].iter().map(|&v| v as f32).collect();
        }
        let n = self.1.len() as f64;
        (0..views[0].len())
            .map(|i| {
                let terms = self.1.iter().map(|&k| views[k][i]);
                (if self.2 == Rule::Mixture {
                    log_sum_exp(&terms.map(|t| t as f32).collect::<Vec<_>>()) - n.ln()
                } else {
                    terms.sum()
                }) as f32
            })
            .collect()
    }
}

/// The project's per-image metrics ([`image_metrics`]) of one way of reading the crops.
#[derive(Default, Clone)]
struct Tally {
    metrics: Vec<ImageMetrics>,
}

impl Tally {
    /// AR@30 of the argmax and of the first mode, mean LL, median argmax error.
    fn summary(&self) -> (f64, f64, f64, f64) {
        let n = self.metrics.len().max(1) as f64;
        let share = |f: &dyn Fn(&ImageMetrics) -> bool| {
            self.metrics.iter().filter(|m| f(m)).count() as f64 / n
        };
        let mut e: Vec<f64> = self.metrics.iter().map(|m| m.argmax_error_deg).collect();
        e.sort_by(f64::total_cmp);
        (
            share(&|m| m.argmax_error_deg <= 30.0),
            share(&|m| m.mode_error_deg <= 30.0),
            self.metrics.iter().map(|m| m.log_likelihood).sum::<f64>() / n,
            e.get(e.len() / 2).copied().unwrap_or(f64::NAN),
        )
    }

    /// Whether the argmax is within 30° of a truth, crop by crop.
    fn right(&self) -> Vec<bool> {
        self.metrics
            .iter()
            .map(|m| m.argmax_error_deg <= 30.0)
            .collect()
    }
}

/// The model, the grid level's cells and the crops' side: what every view is scored with.
struct Study {
    model: Model,
    grid: GridLevel,
    cells: Vec<Rotation3<f64>>,
    centres: Vec<[f64; 4]>,
    size: usize,
}

impl Study {
    /// The log-probabilities of every cell R in each view `k` of `ks`, read at `Q^k · R`, `Q` the
    /// quarter turn about z of `sign`.
    fn views(&self, im: &EvalImage, sign: f64, ks: &[usize]) -> anyhow::Result<Vec<Vec<f64>>> {
        let q = Rotation3::from_axis_angle(&Vector3::z_axis(), sign * FRAC_PI_2);
        let crops: Vec<Vec<u8>> = ks
            .iter()
            .map(|&k| quarter_turns(&im.rgb, self.size, k))
            .collect();
        let refs: Vec<&[u8]> = crops.iter().map(Vec::as_slice).collect();
        let features = self.model.features(&refs)?;
        let rotations: Vec<Vec<[f32; 9]>> = ks
            .iter()
            .map(|&k| {
                let qk = q.powf(k as f64);
                self.cells
                    .iter()
                    .map(|r| to_row_major_f32(&(qk * r)))
                    .collect()
            })
            .collect();
        Ok(self
            .model
            .score_rotations_many(&features, &rotations, Precision::F32)
            .into_iter()
            .map(|l| {
                let lse = log_sum_exp(&l);
                l.iter().map(|&v| v as f64 - lse).collect()
            })
            .collect())
    }

    fn score(&self, tally: &mut Tally, weights: &[f32], im: &EvalImage) -> anyhow::Result<()> {
        let m = image_metrics(&self.grid, &self.centres, weights, &im.equivalents)?;
        tally.metrics.push(m);
        Ok(())
    }

    /// The sign of `Q` that reads the quarter-turned view alone best on `probe`.
    fn sign(&self, probe: &[EvalImage]) -> anyhow::Result<f64> {
        let mut by_sign = Vec::new();
        for sign in [1.0, -1.0] {
            let mut tally = Tally::default();
            for im in probe {
                let views = self.views(im, sign, &[1])?;
                let weights: Vec<f32> = views[0].iter().map(|&v| v as f32).collect();
                self.score(&mut tally, &weights, im)?;
            }
            let ar = tally.summary().0;
            println!(
                "sign {sign:+}: the quarter-turned view alone, AR@30 {ar:.2} on {} crops",
                probe.len()
            );
            by_sign.push((ar, sign));
        }
        Ok(by_sign
            .iter()
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .expect("two signs")
            .1)
    }

    /// Every combination's line for one part's `crops`, with the crops it wins and loses
    /// against the crop alone (the paired comparison that two shares of the same crops need).
    fn report(&self, name: &str, crops: &[&EvalImage], sign: f64) -> anyhow::Result<()> {
        let mut tallies = vec![Tally::default(); COMBINATIONS.len()];
        for im in crops {
            let views = self.views(im, sign, &[0, 1, 2, 3])?;
            for (c, tally) in COMBINATIONS.iter().zip(&mut tallies) {
                self.score(tally, &c.of(&views, &self.cells), im)?;
            }
        }
        let alone = tallies[0].right();
        for (c, t) in COMBINATIONS.iter().zip(&tallies) {
            let (ar, mode_ar, ll, median) = t.summary();
            let (won, lost) = t
                .right()
                .iter()
                .zip(&alone)
                .fold((0, 0), |(w, l), (&r, &a)| {
                    (w + (r && !a) as usize, l + (!r && a) as usize)
                });
            println!(
                "{name}: {:<20} AR@30 {ar:.2} (first mode {mode_ar:.2}), LL {ll:.2}, median error {median:.1}°; against the crop alone +{won} −{lost} ({} crops)",
                c.0,
                t.metrics.len()
            );
        }
        Ok(())
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1).map(std::path::PathBuf::from) else {
        anyhow::bail!(
            "usage: probe_quarter_turns BUNDLE [IMAGES_PER_PART] [LEVEL] [clean|train|held-out]"
        );
    };
    let per_part: usize = args.get(2).map_or(Ok(50), |s| s.parse())?;
    let level: u8 = args.get(3).map_or(Ok(3), |s| s.parse())?;
    let set = args.get(4).map_or("held-out", |s| s.as_str());
    let bundle = ModelBundle::load(&path)?;
    let model: Model = Engine::load_model(&path, EngineConfig::default())?;
    let size = model.input_size();
    let renders = BundleRenders::of(&bundle, 2);
    let images: Vec<EvalImage> = match set {
        "clean" => renders.eval_images(size, per_part, alignist::train::data::EVAL_SEED),
        split => {
            let split: Split = split.parse().map_err(anyhow::Error::msg)?;
            renders.eval_realistic_images(size, per_part, split)
        }
    };
    let grid = GridLevel::new(level)?;
    let study = Study {
        model,
        cells: (0..grid.len() as u64).map(|i| grid.rotation(i)).collect(),
        centres: grid.quaternions(),
        grid,
        size: size as usize,
    };
    let sign = study.sign(&images[..images.len().min(20)])?;
    println!(
        "{per_part} {set} crops per part, level {level} ({} cells; ceiling LL {:.2}, uniform 0), sign {sign:+}",
        study.grid.len(),
        (study.grid.len() as f64).ln()
    );
    let mut names: Vec<String> = images.iter().map(|im| im.object.clone()).collect();
    names.dedup();
    for name in names {
        let crops: Vec<&EvalImage> = images.iter().filter(|im| im.object == name).collect();
        study.report(&name, &crops, sign)?;
    }
    Ok(())
}
