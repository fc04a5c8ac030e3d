//! Where the realistic held-out set's argmax misses go: the depth-flip ambiguity. Mirroring a
//! scene in depth (the camera frame's z → −z) leaves its orthographic silhouette as it is, and
//! for an object with a mirror symmetry S the mirrored object is the object at another rotation,
//! M·R·S (M = diag(1, 1, −1)): a pose that only shading, highlights and perspective tell from the
//! truth. This probe renders the set `alignist-train eval --fresh --realistic` evaluates (same
//! seed: 2⁴⁰ + 1, held-out split, exact boxes), takes the network's argmax on a full grid level,
//! and prints per SYMSOL shape its AR@30, the share within 30° of a depth-flipped equivalent
//! instead, the AR@30 up to the flip, and the argmax errors in 15° bins. S per shape: the tetrahedron's mirror swapping x and y,
//! the cone's mirror in the plane y = 0 (its axis is z), −I for the centrally symmetric cube,
//! icosahedron and cylinder (whose flip is a half-turn about the line of sight).
//! `cargo run --release --example probe_flips [BUNDLE] [IMAGES_PER_OBJECT] [LEVEL]`
use alignist::bundle::model::ModelBundle;
use alignist::data::realism::Split;
use alignist::net::ProjectedGrid;
use alignist::train::data::BundleRenders;
use nalgebra::{Matrix3, Rotation3};

/// An improper symmetry of a SYMSOL shape, by name.
fn mirror_symmetry(object: &str) -> Option<Matrix3<f64>> {
    match object {
        "tet" => Some(Matrix3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)),
        "cone" => Some(Matrix3::from_diagonal(&nalgebra::Vector3::new(
            1.0, -1.0, 1.0,
        ))),
        "cube" | "icosa" | "cyl" => Some(-Matrix3::identity()),
        _ => None,
    }
}

fn nearest_deg(r: &Rotation3<f64>, set: &[Rotation3<f64>]) -> f64 {
    set.iter()
        .map(|g| (r.inverse() * g).angle().to_degrees())
        .fold(f64::INFINITY, f64::min)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = std::path::PathBuf::from(args.get(1).map_or("models/symsol1", |s| s.as_str()));
    let per_object: usize = args.get(2).map_or(Ok(50), |s| s.parse())?;
    let level: u8 = args.get(3).map_or(Ok(3), |s| s.parse())?;
    let bundle = ModelBundle::load(&path)?;
    let config = &bundle.manifest.network;
    let renders = BundleRenders::of(&bundle, 2);
    let images = renders.eval_realistic_images(config.image_size, per_object, Split::HeldOut);
    let projected = ProjectedGrid::new(&bundle.network, config, level)?;
    let depth_mirror = Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 1.0, -1.0));
    // Per object: images, right, flipped (not right), right up to the flip.
    let mut tally: std::collections::BTreeMap<String, [usize; 4]> = Default::default();
    let mut misses: std::collections::BTreeMap<String, Vec<f64>> = Default::default();
    let crops: Vec<&[u8]> = images.iter().map(|i| i.rgb.as_slice()).collect();
    let guesses = projected.argmax_of_crops(&bundle.network, &crops, config.image_size as usize);
    for (im, guess) in images.iter().zip(guesses) {
        let t = tally.entry(im.object.clone()).or_default();
        t[0] += 1;
        let error = nearest_deg(&guess, &im.equivalents);
        misses.entry(im.object.clone()).or_default().push(error);
        let right = error <= 30.0;
        let flipped = mirror_symmetry(&im.object).is_some_and(|s| {
            let flips: Vec<Rotation3<f64>> = im
                .equivalents
                .iter()
                .map(|g| Rotation3::from_matrix_unchecked(depth_mirror * g.matrix() * s))
                .collect();
            nearest_deg(&guess, &flips) <= 30.0
        });
        t[1] += right as usize;
        t[2] += (flipped && !right) as usize;
        t[3] += (right || flipped) as usize;
    }
    println!(
        "{} held-out realistic crops per object, level {level}, argmax of {}:",
        per_object,
        path.display()
    );
    println!("  object  AR@30  flipped@30  AR@30 up to the depth flip");
    let mut all = [0usize; 4];
    for (object, t) in &tally {
        let share = |k: usize| t[k] as f64 / t[0] as f64;
        println!(
            "  {object:6}  {:.3}  {:.3}       {:.3}",
            share(1),
            share(2),
            share(3)
        );
        for k in 0..4 {
            all[k] += t[k];
        }
    }
    println!("  argmax errors per 15° bin (0–15°, 15–30°, …):");
    for (object, errors) in &misses {
        let mut bins = [0usize; 12];
        for e in errors {
            bins[((e / 15.0) as usize).min(11)] += 1;
        }
        println!("  {object:6}  {bins:?}");
    }
    let share = |k: usize| all[k] as f64 / all[0] as f64;
    println!(
        "  all     {:.3}  {:.3}       {:.3}",
        share(1),
        share(2),
        share(3)
    );
    Ok(())
}
