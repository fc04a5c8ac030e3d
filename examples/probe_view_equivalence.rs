//! How many of a part's crops no image could answer: poses that its view cannot tell apart.
//!
//! A part with no symmetry has one truth per crop, but a view may not show what breaks its near
//! symmetry (a mug's handle behind its body): then every turn about the near symmetry's axis
//! that keeps the handle hidden looks the same, and an answer can be right only by chance. BOP
//! scores such poses with the Visible Surface Discrepancy (VSD: Hodaň et al. 2016), which counts
//! a pose as right when its visible surface matches the truth's. This probe applies that test to
//! the part alone (no occluders, no realism: the ambiguity of the shape itself), rendered through
//! one square camera looking at its centre, on the crops `alignist-train eval --fresh
//! --realistic` scores (seed 2⁴⁰ + 1, exact boxes):
//!
//! - VSD between two renders: over the pixels either shows, the share where only one shows the
//!   part or their depths differ by more than `τ` = 5 % of the part's diameter; two poses *look
//!   the same* below `VSD_SAME` (0.10; BOP's recall averages thresholds 0.05–0.5).
//! - A crop is *view-ambiguous* when some twin of its truth at least 30° from it
//!   (`R_t·S` for the near symmetry's recorded turns `S`, every 10° for a cone) looks the same.
//! - The strict AR@30 that a model seeing only the part could reach: on a view-ambiguous crop,
//!   a guess among the poses that look the same is within 30° of the truth with probability
//!   (those within 30°) / (all of them), so the bound is the mean of that over the crops (1 on
//!   the others).
//! - The network's argmax: strict AR@30 (within 30° of the truth) and view AR@30 (within 30° of
//!   the truth or of a twin that looks the same, or itself looking the same as the truth).
//!
//! `cargo run --release --example probe_view_equivalence BUNDLE [IMAGES_PER_PART] [LEVEL] [train|held-out] [VSD_SAME] [TAU]`
use alignist::bundle::model::ModelBundle;
use alignist::cad::Mesh;
use alignist::cad::{Camera, Pose, Render, RenderOptions, render};
use alignist::data::realism::Split;
use alignist::net::ProjectedGrid;
use nalgebra::{Rotation3, Vector3};

/// Side of the probe's renders in pixels.
const SIDE: u32 = 96;
/// VSD below which two poses look the same (default; the fifth argument).
const VSD_SAME: f64 = 0.10;
/// VSD's depth tolerance as a share of the part's diameter (default; the sixth argument).
const TAU_OF_DIAMETER: f64 = 0.05;

/// The part alone at rotation `r`, its centre 4 radii in front of a camera whose view it fills.
fn view(mesh: &Mesh, radius: f64, r: &Rotation3<f64>) -> Render {
    let distance = 4.0 * radius;
    let focal = SIDE as f64 / 2.0 * distance / (1.2 * radius);
    let pose = Pose {
        rotation: *r,
        translation: Vector3::new(0.0, 0.0, distance),
    };
    render(
        mesh,
        &Camera::square_with_focal(SIDE, focal),
        &pose,
        &RenderOptions::default(),
    )
}

/// Visible Surface Discrepancy of two renders with depth tolerance `tau`.
fn vsd(a: &Render, b: &Render, tau: f64) -> f64 {
    let (mut union, mut wrong) = (0usize, 0usize);
    for i in 0..a.mask.len() {
        match (a.mask[i], b.mask[i]) {
            (false, false) => continue,
            (true, true) => wrong += ((a.depth[i] - b.depth[i]).abs() as f64 > tau) as usize,
            _ => wrong += 1,
        }
        union += 1;
    }
    if union == 0 {
        0.0
    } else {
        wrong as f64 / union as f64
    }
}

fn angle_deg(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
    (a.inverse() * b).angle().to_degrees()
}

/// One part's crops, counted.
#[derive(Default)]
struct Tally {
    crops: usize,
    ambiguous: usize,
    bound: f64,
    strict: usize,
    view: usize,
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1).map(std::path::PathBuf::from) else {
        anyhow::bail!(
            "usage: probe_view_equivalence BUNDLE [IMAGES_PER_PART] [LEVEL] [train|held-out] [VSD_SAME] [TAU]"
        );
    };
    let per_part: usize = args.get(2).map_or(Ok(100), |s| s.parse())?;
    let level: u8 = args.get(3).map_or(Ok(3), |s| s.parse())?;
    let split: Split = args
        .get(4)
        .map_or("held-out", |s| s.as_str())
        .parse()
        .map_err(anyhow::Error::msg)?;
    let same: f64 = args.get(5).map_or(Ok(VSD_SAME), |s| s.parse())?;
    let tau_of_diameter: f64 = args.get(6).map_or(Ok(TAU_OF_DIAMETER), |s| s.parse())?;
    let bundle = ModelBundle::load(&path)?;
    let config = &bundle.manifest.network;
    let renders = alignist::train::data::BundleRenders::of(&bundle, 2);
    let images = renders.eval_realistic_images(config.image_size, per_part, split);
    let projected = ProjectedGrid::new(&bundle.network, config, level)?;
    println!(
        "{per_part} {split:?} realistic crops per part, exact boxes, level {level}, argmax of {}; \
         VSD of the part alone at {SIDE} px, tau {tau_of_diameter} of the diameter, same below {same}",
        path.display()
    );
    println!(
        "| part | twins | view-ambiguous crops | strict AR@30 bound | argmax strict AR@30 | argmax view AR@30 |"
    );
    println!("|---|---|---|---|---|---|");
    for (part, name) in renders.names.iter().enumerate() {
        let mesh = &bundle.experts[part].mesh;
        let radius = mesh
            .vertices
            .iter()
            .map(|v| v.cast::<f64>().norm())
            .fold(0.0, f64::max);
        let tau = tau_of_diameter * 2.0 * radius;
        let twins = bundle.experts[part].near_twins();
        let crops: Vec<_> = images.iter().filter(|im| im.object == *name).collect();
        let mut tally = Tally::default();
        let rgb: Vec<&[u8]> = crops.iter().map(|i| i.rgb.as_slice()).collect();
        let guesses = projected.argmax_of_crops(&bundle.network, &rgb, config.image_size as usize);
        for (im, guess) in crops.iter().zip(guesses) {
            let truth = im
                .equivalents
                .iter()
                .min_by(|a, b| angle_deg(a, &guess).total_cmp(&angle_deg(b, &guess)))
                .expect("every crop has a truth");
            let seen = view(mesh, radius, truth);
            let looks_same = |r: &Rotation3<f64>| vsd(&seen, &view(mesh, radius, r), tau) < same;
            let alike: Vec<Rotation3<f64>> = twins
                .iter()
                .map(|s| truth * s)
                .filter(|r| looks_same(r))
                .collect();
            let apart: Vec<f64> = alike.iter().map(|r| angle_deg(truth, r)).collect();
            let near = 1 + apart.iter().filter(|&&a| a <= 30.0).count();
            tally.crops += 1;
            tally.ambiguous += apart.iter().any(|&a| a > 30.0) as usize;
            tally.bound += near as f64 / (1 + alike.len()) as f64;
            let strict = angle_deg(truth, &guess) <= 30.0;
            let near_alike = alike.iter().any(|r| angle_deg(r, &guess) <= 30.0);
            tally.strict += strict as usize;
            tally.view += (strict || near_alike || looks_same(&guess)) as usize;
        }
        let n = tally.crops.max(1) as f64;
        println!(
            "| {name} | {} | {:.2} | {:.2} | {:.2} | {:.2} |",
            twins.len(),
            tally.ambiguous as f64 / n,
            tally.bound / n,
            tally.strict as f64 / n,
            tally.view as f64 / n
        );
    }
    Ok(())
}
