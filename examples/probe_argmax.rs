//! Probe: where the level-3 argmax (the AR@30 point estimate) of a bundle goes wrong on one shape.
//! `cargo run --release --example probe_argmax MODEL_DIR SHAPE` prints, for each of the 50 fresh
//! test crops of SHAPE (seed 2⁴⁰, as `alignist-train eval`), the argmax's error, the angle
//! between its symmetry axis (object z) and the true one, the view's tilt, and the mass within
//! 15° of the ground truths beside the mass within 15° of the argmax: a failure with most of the
//! mass on the truth and little around the argmax is an isolated spike, not a wrong mode.
use alignist::bundle::model::ModelBundle;
use alignist::engine::{Engine, EngineConfig};
use alignist::so3::metrics::error_to_nearest_deg;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dir = std::path::Path::new(&args[1]);
    let shape = &args[2];
    let bundle = ModelBundle::load(dir).unwrap();
    let renders = alignist::train::data::BundleRenders::of(&bundle, 4);
    let model = Engine::load_model(dir, EngineConfig::default()).unwrap();
    let images = renders.eval_images(model.input_size(), 50, 1 << 40);
    let grid = model.grid(3).unwrap().clone();
    for im in images.iter().filter(|im| im.object == *shape) {
        let f = model
            .features(&[&im.rgb])
            .expect("crops of the input side")
            .swap_remove(0);
        let d = model.distribution(&f, 3, None).unwrap();
        let p = &d.probability;
        let best = (0..p.len()).max_by(|&a, &b| p[a].total_cmp(&p[b])).unwrap();
        let r = grid.rotation(best as u64);
        let err = error_to_nearest_deg(&r, &im.equivalents);
        // The axis (object z) in the camera frame: predicted vs true, up to a flip.
        let pa = r * nalgebra::Vector3::z();
        let ta = im.equivalents[0] * nalgebra::Vector3::z();
        let axis = pa.dot(&ta).abs().min(1.0).acos().to_degrees();
        // Mass within 15° of the true set vs the argmax's neighbourhood.
        let mut near_true = 0.0;
        let mut near_max = 0.0;
        for (i, &pi) in p.iter().enumerate() {
            let ri = grid.rotation(i as u64);
            if error_to_nearest_deg(&ri, &im.equivalents) < 15.0 {
                near_true += pi as f64;
            }
            if alignist::so3::geodesic_angle(&ri, &r).to_degrees() < 15.0 {
                near_max += pi as f64;
            }
        }
        let view = ta.z.abs().acos().to_degrees(); // angle between the axis and the optical axis
        println!(
            "{} err {:6.1}° axis {:5.1}° view(axis vs optical) {:5.1}° mass≤15° true {:.3} argmax {:.3} pmax {:.5}{}",
            shape,
            err,
            axis,
            view,
            near_true,
            near_max,
            p[best],
            if err > 30.0 { "  FAIL" } else { "" }
        );
    }
}
