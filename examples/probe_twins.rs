//! Where a part's half-turn misses go. For every crop of a realistic set (the sets `alignist-train
//! eval --fresh --realistic` scores: same seed 2⁴⁰ + 1, exact boxes) the network's argmax on a
//! full grid level is compared with the nearest equivalent truth R_t. A half-turn miss (≥ 150°
//! from every truth, `HALF_TURN_DEG`) is the turn D = R_t⁻¹·R_argmax in the object's frame, and
//! R_argmax·R_t⁻¹ in the camera's. Per part this prints AR@30, the half-turn share, and for the
//! misses the axis their turns share (the leading eigenvector of Σ a·aᵀ over their axes a, with
//! the share of Σ|a|² it holds: 1 when every miss turns about one line, 1/3 when spread evenly)
//! in each frame, the share of crops answered upside down (the truth turned half a turn about
//! the camera's line of sight), the angle from that object-frame axis to the part's recorded near-symmetry
//! twin (when its experts record one), and the share of crops right up to those twins (within
//! 30° of some R_t·S). Twin sampling (`new --twin-share`) draws negatives at R_t·S, so it can only
//! help when the misses sit there.
//! `cargo run --release --example probe_twins BUNDLE [IMAGES_PER_PART] [LEVEL] [train|held-out]`
use alignist::bundle::model::ModelBundle;
use alignist::data::realism::Split;
use alignist::net::ProjectedGrid;
use alignist::so3::metrics::HALF_TURN_DEG;
use alignist::train::data::BundleRenders;
use nalgebra::{Matrix3, Rotation3, SymmetricEigen, Vector3};
use std::f64::consts::PI;

/// The truth nearest `guess` among `truths`, and the angle to it in degrees.
fn nearest<'a>(guess: &Rotation3<f64>, truths: &'a [Rotation3<f64>]) -> (&'a Rotation3<f64>, f64) {
    truths
        .iter()
        .map(|t| (t, (t.inverse() * guess).angle().to_degrees()))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("every crop has a truth")
}

/// The line the axes share: the leading eigenvector of Σ a·aᵀ and its share of the trace.
fn shared_axis(axes: &[Vector3<f64>]) -> Option<(Vector3<f64>, f64)> {
    if axes.is_empty() {
        return None;
    }
    let scatter: Matrix3<f64> = axes.iter().map(|a| a * a.transpose()).sum();
    let eigen = SymmetricEigen::new(scatter);
    let (k, top) = eigen
        .eigenvalues
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))?;
    Some((
        eigen.eigenvectors.column(k).into_owned(),
        top / scatter.trace(),
    ))
}

fn unit_axis(r: &Rotation3<f64>) -> Vector3<f64> {
    r.axis().map_or(Vector3::z(), |a| a.into_inner())
}

/// How many of the misses `turns` (each R_t⁻¹·R_argmax) lie within 30° of `half_turn`.
fn own_twin(turns: &[Rotation3<f64>], half_turn: &Rotation3<f64>) -> usize {
    turns
        .iter()
        .filter(|d| (half_turn.inverse() * *d).angle().to_degrees() <= 30.0)
        .count()
}

fn line_angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.normalize()
        .dot(&b.normalize())
        .abs()
        .min(1.0)
        .acos()
        .to_degrees()
}

/// One part's argmax answers, counted.
#[derive(Default)]
struct Tally {
    right: usize,
    right_up_to_twins: usize,
    /// `R_t⁻¹·R̂` of each half-turn miss.
    object_misses: Vec<Rotation3<f64>>,
    /// The axis of `R̂·R_t⁻¹` of each half-turn miss.
    camera_axes: Vec<Vector3<f64>>,
    /// Misses within 30° of the truth turned half a turn about the line of sight.
    upside_down: usize,
}

impl Tally {
    fn add(
        &mut self,
        guess: &Rotation3<f64>,
        equivalents: &[Rotation3<f64>],
        twins: &[Rotation3<f64>],
    ) {
        let (truth, error) = nearest(guess, equivalents);
        self.right += (error <= 30.0) as usize;
        let twinned: Vec<Rotation3<f64>> = equivalents
            .iter()
            .flat_map(|t| twins.iter().map(move |s| t * s))
            .collect();
        self.right_up_to_twins +=
            (error <= 30.0 || (!twinned.is_empty() && nearest(guess, &twinned).1 <= 30.0)) as usize;
        if error >= HALF_TURN_DEG {
            self.object_misses.push(truth.inverse() * guess);
            self.camera_axes.push(unit_axis(&(guess * truth.inverse())));
            let upside_down = Rotation3::from_axis_angle(&Vector3::z_axis(), PI);
            self.upside_down += ((upside_down.inverse() * guess * truth.inverse())
                .angle()
                .to_degrees()
                <= 30.0) as usize;
        }
    }

    fn print(&self, name: &str, twins: &[Rotation3<f64>], n: f64) {
        let object_axes: Vec<Vector3<f64>> = self.object_misses.iter().map(unit_axis).collect();
        println!(
            "{name}: AR@30 {:.2}, half-turn misses {:.2}, right up to the recorded twins {:.2} ({} twins)",
            self.right as f64 / n,
            object_axes.len() as f64 / n,
            self.right_up_to_twins as f64 / n,
            twins.len()
        );
        println!(
            "  misses within 30° of the truth turned half a turn about the line of sight: {:.2} of the crops",
            self.upside_down as f64 / n
        );
        for (frame, axes) in [("object", &object_axes), ("camera", &self.camera_axes)] {
            let Some((axis, share)) = shared_axis(axes) else {
                continue;
            };
            println!(
                "  misses' shared axis, {frame} frame: ({:+.2}, {:+.2}, {:+.2}), share {share:.2}",
                axis.x, axis.y, axis.z
            );
            if frame != "object" {
                continue;
            }
            let farthest = twins.iter().max_by(|a, b| a.angle().total_cmp(&b.angle()));
            if let Some(s) = farthest.filter(|s| s.angle().to_degrees() > 150.0) {
                let a = unit_axis(s);
                println!(
                    "    {:.0}° from the recorded twin's axis ({:+.2}, {:+.2}, {:+.2})",
                    line_angle_deg(&axis, &a),
                    a.x,
                    a.y,
                    a.z
                );
            }
            let half_turn = Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), PI);
            println!(
                "    misses within 30° of R_t·(half-turn about it): {:.2} of the crops",
                own_twin(&self.object_misses, &half_turn) as f64 / n
            );
        }
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1).map(std::path::PathBuf::from) else {
        anyhow::bail!("usage: probe_twins BUNDLE [IMAGES_PER_PART] [LEVEL] [train|held-out]");
    };
    let per_part: usize = args.get(2).map_or(Ok(50), |s| s.parse())?;
    let level: u8 = args.get(3).map_or(Ok(3), |s| s.parse())?;
    let split: Split = args
        .get(4)
        .map_or("held-out", |s| s.as_str())
        .parse()
        .map_err(anyhow::Error::msg)?;
    let bundle = ModelBundle::load(&path)?;
    let config = &bundle.manifest.network;
    let renders = BundleRenders::of(&bundle, 2);
    let images = renders.eval_realistic_images(config.image_size, per_part, split);
    let projected = ProjectedGrid::new(&bundle.network, config, level)?;
    println!(
        "{} {split:?} realistic crops per part, exact boxes, level {level}, argmax of {}",
        per_part,
        path.display()
    );
    for (part, name) in renders.names.iter().enumerate() {
        let twins = bundle.experts[part].near_twins();
        let crops: Vec<_> = images.iter().filter(|im| im.object == *name).collect();
        let mut tally = Tally::default();
        let rgb: Vec<&[u8]> = crops.iter().map(|i| i.rgb.as_slice()).collect();
        let guesses = projected.argmax_of_crops(&bundle.network, &rgb, config.image_size as usize);
        for (im, guess) in crops.iter().zip(guesses) {
            tally.add(&guess, &im.equivalents, &twins);
        }
        tally.print(name, &twins, crops.len() as f64);
    }
    Ok(())
}
