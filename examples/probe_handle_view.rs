//! Where a part's argmax misses lie against the direction of its farthest feature from its z
//! axis (a mug's handle), on the crops an evaluation report scored.
//!
//! A mug is nearly a cone about its z axis; its handle breaks that. If its misses came from
//! views that hide the handle, they would gather where the handle points away from the camera.
//! This probe finds the handle's direction `h` in the mesh (the mean radial direction of the 1 %
//! of vertices farthest from the axis through the vertices' median x and y), and for each crop
//! of `alignist-train eval --out REPORT` takes `h·ẑ` in the camera frame (`R h`; the camera looks
//! along +z, so −1 is the handle toward the camera, +1 behind the body) and prints AR@30 per bin
//! of it, with the argmax errors of the misses on each side. Where the report holds the argmax's
//! rotation, it also prints AR@30 by how far the view looks down the mug's axis (`|(R ẑ)·ẑ|`:
//! 0 a side view, 1 into or under it) and, for each half-turn miss, the turn's axis in the mesh's
//! frame against the mug's axis and the handle.
//!
//! `cargo run --release --example probe_handle_view REPORT.json MESH`
use std::path::Path;

use alignist::cad::Mesh;
use anyhow::{Context, Result, bail};
use nalgebra::{Quaternion, Unit, UnitQuaternion, Vector3};

/// Bins of `h·ẑ`, from the handle toward the camera to the handle behind the body.
const BINS: [(f64, f64); 5] = [
    (-1.0, -0.5),
    (-0.5, 0.0),
    (0.0, 0.5),
    (0.5, 0.8),
    (0.8, 1.0),
];

/// The unit direction, in the mesh's frame, of its farthest vertices from its z axis.
fn handle_direction(mesh: &Mesh) -> Vector3<f64> {
    let median = |f: fn(&Vector3<f32>) -> f32| {
        let mut v: Vec<f64> = mesh.vertices.iter().map(|p| f(p) as f64).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (cx, cy) = (median(|p| p.x), median(|p| p.y));
    let mut radial: Vec<(f64, Vector3<f64>)> = mesh
        .vertices
        .iter()
        .map(|p| {
            let d = Vector3::new(p.x as f64 - cx, p.y as f64 - cy, 0.0);
            (d.norm(), d)
        })
        .collect();
    radial.sort_by(|a, b| b.0.total_cmp(&a.0));
    let far = radial.len().div_ceil(100);
    radial[..far]
        .iter()
        .map(|(_, d)| d)
        .sum::<Vector3<f64>>()
        .normalize()
}

/// One scored crop: its ground truth, its argmax's error and, where recorded, its argmax.
struct Crop {
    truth: UnitQuaternion<f64>,
    error: f64,
    argmax: Option<UnitQuaternion<f64>>,
}

fn quaternion(value: &serde_json::Value) -> Option<UnitQuaternion<f64>> {
    let q: Vec<f64> = value
        .as_array()?
        .iter()
        .filter_map(|x| x.as_f64())
        .collect();
    let [w, x, y, z] = q[..] else { return None };
    Some(UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)))
}

fn crops_of(images: &[serde_json::Value], report: &str) -> Result<Vec<Crop>> {
    images
        .iter()
        .map(|i| {
            let truth = quaternion(&i["truth"])
                .with_context(|| format!("{report}: an image without a (w, x, y, z) truth"))?;
            let error = i["argmax_error_deg"]
                .as_f64()
                .with_context(|| format!("{report}: an image without argmax_error_deg"))?;
            let argmax = quaternion(&i["argmax"]);
            Ok(Crop {
                truth,
                error,
                argmax,
            })
        })
        .collect()
}

/// AR@30 per bin of `key` over `crops`.
fn print_bins(crops: &[Crop], bins: &[(f64, f64)], label: &str, key: impl Fn(&Crop) -> f64) {
    for &(lo, hi) in bins {
        let inside: Vec<&Crop> = crops
            .iter()
            .filter(|c| key(c) >= lo && (key(c) < hi || hi == 1.0))
            .collect();
        let right = inside.iter().filter(|c| c.error < 30.0).count();
        println!(
            "  {label} in [{lo:+.1}, {hi:+.1}]: {:3} crops, AR@30 {:.2}",
            inside.len(),
            right as f64 / inside.len().max(1) as f64
        );
    }
}

/// For each half-turn miss: the turn `R_truth⁻¹ R_argmax`'s axis in the mesh's frame, its
/// `|·z|` (1: about the mug's axis) and `|·h|` (1: about the handle), and `h·ẑ` of the view.
fn print_half_turns(crops: &[Crop], h: &Vector3<f64>) {
    let z = Vector3::z();
    for c in crops.iter().filter(|c| c.error >= 150.0) {
        let Some(argmax) = c.argmax else { continue };
        let turn = c.truth.inverse() * argmax;
        let axis: Unit<Vector3<f64>> = turn.axis().unwrap_or(Vector3::x_axis());
        println!(
            "  half-turn {:5.1}°: axis ({:+.2}, {:+.2}, {:+.2}), |axis·z| {:.2}, |axis·h| {:.2}, \
             view h·z {:+.2}, view |z·z| {:.2}",
            c.error,
            axis.x,
            axis.y,
            axis.z,
            axis.dot(&z).abs(),
            axis.dot(h).abs(),
            (c.truth * h).z,
            (c.truth * z).z.abs()
        );
    }
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let [_, report, mesh] = &args[..] else {
        bail!("usage: probe_handle_view REPORT.json MESH");
    };
    let mesh = Mesh::load(Path::new(mesh)).with_context(|| format!("reading {mesh}"))?;
    let h = handle_direction(&mesh);
    println!(
        "handle direction in the mesh's frame: ({:.3}, {:.3}, {:.3})",
        h.x, h.y, h.z
    );
    let text = std::fs::read_to_string(report).with_context(|| format!("reading {report}"))?;
    let sets: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {report}"))?;
    for set in sets
        .as_array()
        .context("the report is not a list of sets")?
    {
        let name = set["set"].as_str().unwrap_or("?");
        let images = set["report"]["images"]
            .as_array()
            .with_context(|| format!("{report}: set {name} has no report.images"))?;
        let crops = crops_of(images, report)?;
        println!("{name}: {} crops", crops.len());
        print_bins(&crops, &BINS, "h·z", |c| (c.truth * h).z);
        for (side, toward) in [
            ("toward the camera (h·z < 0)", true),
            ("away (h·z ≥ 0)", false),
        ] {
            let mut misses: Vec<f64> = crops
                .iter()
                .filter(|c| ((c.truth * h).z < 0.0) == toward && c.error >= 30.0)
                .map(|c| c.error.round())
                .collect();
            misses.sort_by(f64::total_cmp);
            let half_turns = misses.iter().filter(|e| **e >= 150.0).count();
            println!(
                "  misses, handle {side}: {} ({} at 150° or more): {misses:?}",
                misses.len(),
                half_turns
            );
        }
        if crops.iter().any(|c| c.argmax.is_some()) {
            let views = [(0.0, 0.3), (0.3, 0.6), (0.6, 0.8), (0.8, 1.0)];
            print_bins(&crops, &views, "|z·z|", |c| {
                (c.truth * Vector3::z()).z.abs()
            });
            print_half_turns(&crops, &h);
        }
    }
    Ok(())
}
