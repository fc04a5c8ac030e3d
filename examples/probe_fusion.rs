//! Probe: the fused depth term along each test crop's set of equivalent ground truths.
//! `cargo run --release --example probe_fusion MODEL_DIR OBJECT N` prints, per crop, the spread
//! (max − min, std) of κ·(−U) over the level-3 cells of the equivalents, their mean below the
//! grid's best term, and the translation error of τ₀ at the ground truth.
//! `probe_fusion --table-time` prints how long the cylinder's view table takes to build.
use alignist::bundle::model::ModelBundle;
use alignist::engine::{CropBox, DepthInput, Engine, EngineConfig, SeenPoints, back_project};
use alignist::so3::to_row_major_f32;
use alignist::train::depth_eval::depth_eval_images;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some("--table-time") {
        let (mesh, _) = alignist::cad::Shape::Cylinder.mesh().normalised();
        let started = std::time::Instant::now();
        let _ = alignist::engine::ViewTable::build(&mesh);
        println!(
            "view table of the cylinder built in {:.2} s",
            started.elapsed().as_secs_f64()
        );
        return;
    }
    let dir = std::path::Path::new(&args[1]);
    let object_name = &args[2];
    let n: usize = args[3].parse().unwrap();
    let bundle = ModelBundle::load(dir).unwrap();
    let renders = alignist::train::data::BundleRenders::of(&bundle, 4);
    let model = Engine::load_model(dir, EngineConfig::default()).unwrap();
    let images = depth_eval_images(&model, &renders, n, 1 << 40).unwrap();
    let grid = model.grid(3).unwrap().clone();
    let all: Vec<[f32; 9]> = (0..grid.len() as u64)
        .map(|c| to_row_major_f32(&grid.rotation(c)))
        .collect();
    for im in images
        .iter()
        .filter(|im| model.objects[im.object].name == *object_name)
    {
        let object = &model.objects[im.object];
        let whole = CropBox::pixels(0, 0, im.depth.width, im.depth.height);
        let pts = back_project(&im.depth, &im.intrinsics, &whole, None, 256, "depth").unwrap();
        let seen = SeenPoints::Camera(object.fusion.camera_points(&pts, "depth").unwrap());
        let input = DepthInput {
            object,
            points: &seen,
        };
        let terms = input
            .cell_log_measure(&grid, &all, &Default::default())
            .unwrap();
        let best = terms.iter().copied().fold(f32::MIN, f32::max);
        let mut cells: Vec<u64> = im.equivalents.iter().map(|g| grid.cell_of(g)).collect();
        cells.sort();
        cells.dedup();
        let gt: Vec<f32> = im
            .equivalents
            .iter()
            .map(|g| terms[grid.cell_of(g) as usize] - best)
            .collect();
        let mean = gt.iter().sum::<f32>() / gt.len() as f32;
        let sd = (gt.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / gt.len() as f32).sqrt();
        let mx = gt.iter().copied().fold(f32::MIN, f32::max);
        let mn = gt.iter().copied().fold(f32::MAX, f32::min);
        // exact GT rotations (not cell centres)
        let exact: Vec<[f32; 9]> = im.equivalents.iter().map(to_row_major_f32).collect();
        let ex = input.log_measure(&exact);
        let exmax = ex.iter().copied().fold(f32::MIN, f32::max);
        let exmin = ex.iter().copied().fold(f32::MAX, f32::min);
        let fit = input.fit(&exact[0]).unwrap();
        let SeenPoints::Camera(cp) = &seen else {
            unreachable!()
        };
        let t0 = object
            .fusion
            .initial_translation(cp, &nalgebra::Matrix3::from_row_slice(&exact[0]));
        let dt = (t0 - fit.0).norm();
        println!(
            "  tau0 - fit = {:.4} radii; centroid z {:.2}",
            dt, cp.centroid.z
        );
        println!(
            "{} eq {} cells {}: cell terms rel best mean {:.2} sd {:.2} [{:.2}, {:.2}]; exact −U [{:.3}, {:.3}] fitted {:.3}",
            object.name,
            im.equivalents.len(),
            cells.len(),
            mean,
            sd,
            mn,
            mx,
            exmin,
            exmax,
            fit.1
        );
    }
}
