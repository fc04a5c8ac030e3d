//! RGB-D fusion with a real SDF expert (the shipped cube's): from a rendered depth image, the
//! translation is found within 5 % of the object's radius and the depth term's best rotation is
//! one of the cube's equivalents, with clean and with noisy depth.

use std::path::Path;

use alignist::bundle::experts::ExpertSet;
use alignist::cad::{RenderOptions, render};
use alignist::data::virtual_crop::{frame_camera, object_pixel_box, random_placement};
use alignist::engine::{CropBox, DepthFusion, DepthMap, Intrinsics, back_project};
use alignist::so3::{GridLevel, geodesic_angle, to_row_major_f32};
use alignist::train::depth_eval::spoil;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

#[test]
fn depth_fusion_finds_the_translation_and_the_rotation_of_a_rendered_cube() {
    let set = ExpertSet::load(Path::new("models/symsol1/experts/cube")).unwrap();
    let mesh = set.mesh.clone();
    let symmetries = set.symmetries();
    let scale = set.manifest.object.normalisation.scale;
    let fusion = DepthFusion::new(set);
    fusion.warm();
    let camera = frame_camera();
    let intrinsics = Intrinsics::from(&camera);
    let grid = GridLevel::new(3).unwrap();
    let rotations = grid.matrices_f32();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for _ in 0..4 {
        let pose = random_placement(&mut rng);
        let image = render(&mesh, &camera, &pose, &RenderOptions::default());
        // The render is of the normalised mesh: depth in the source mesh's units.
        let clean = DepthMap {
            width: image.width,
            height: image.height,
            values: image.depth.iter().map(|z| z * scale as f32).collect(),
        };
        let [x, y, width, height] = object_pixel_box(&mesh, &pose, &camera);
        let bbox = CropBox::pixels(x, y, width, height);
        // Clean, then σ = 2 % of the radius with 10 % of the pixels missing.
        for (sigma, missing) in [(0.0, 0.0), (0.02, 0.1)] {
            let map = spoil(&clean, sigma * scale, missing, &mut rng);
            let points = back_project(&map, &intrinsics, &bbox, None, 256, "box").unwrap();
            let seen = fusion.camera_points(&points, "depth.scale").unwrap();
            let (tau, _) = fusion.fit_translation(&seen, &to_row_major_f32(&pose.rotation));
            let error = (tau.cast::<f64>() - pose.translation).norm();
            assert!(error < 0.05, "σ {sigma}: translation off by {error} radii");
            let terms = fusion.posed_log_measure(&seen, &rotations);
            let best = (0..terms.len())
                .max_by(|&a, &b| terms[a].total_cmp(&terms[b]))
                .unwrap();
            let r = grid.rotation(best as u64);
            let nearest = symmetries
                .iter()
                .map(|s| geodesic_angle(&r, &(pose.rotation * s)).to_degrees())
                .fold(f64::INFINITY, f64::min);
            assert!(
                nearest < 15.0,
                "σ {sigma}: best cell {nearest}° from an equivalent"
            );
        }
    }
}

/// The view table's `τ₀` on a cylinder rendered close up (2.7 radii, where a camera sees much
/// less than a hemisphere) and further away (8 radii): within 3 % of the radius at the true
/// rotation, where the far layer alone (the table before it had distances) is off by several %.
#[test]
fn the_view_table_places_a_close_cylinder_from_its_depth_alone() {
    use alignist::cad::{Camera, Pose, Shape};
    use alignist::engine::{CameraPoints, ViewTable};
    use alignist::so3::haar_rotation;
    let (mesh, _) = Shape::Cylinder.mesh().normalised();
    let table = ViewTable::build(&mesh);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (mut layered, mut far) = (Vec::new(), Vec::new());
    for distance in [2.7, 8.0] {
        let focal = 0.45 * 160.0 * f64::sqrt(distance * distance - 1.0);
        let camera = Camera::square_with_focal(160, focal);
        for _ in 0..8 {
            let pose = Pose {
                rotation: haar_rotation(&mut rng),
                translation: nalgebra::Vector3::new(0.0, 0.0, distance),
            };
            let image = render(&mesh, &camera, &pose, &RenderOptions::default());
            let map = DepthMap {
                width: image.width,
                height: image.height,
                values: image.depth.clone(),
            };
            let whole = CropBox::pixels(0, 0, map.width, map.height);
            let back =
                back_project(&map, &Intrinsics::from(&camera), &whole, None, 256, "d").unwrap();
            let seen = CameraPoints {
                points: back.points.iter().map(|p| p.cast::<f32>()).collect(),
                centroid: back.centroid.cast(),
            };
            let r = pose.rotation.matrix().cast::<f32>();
            let truth = pose.translation.cast::<f32>();
            let tau = table.initial_translation(&seen, &r);
            layered.push((distance, (tau - truth).norm()));
            let view = (r.transpose() * seen.centroid.normalize()).cast::<f64>();
            let tau_far = seen.centroid - r * table.centroid(&view, 20.0);
            far.push((distance, (tau_far - truth).norm()));
        }
    }
    let worst = layered.iter().map(|e| e.1).fold(0f32, f32::max);
    assert!(worst < 0.03, "τ₀ off by up to {worst} radii: {layered:?}");
    let mean_close = |errors: &[(f64, f32)]| {
        let close: Vec<f32> = errors.iter().filter(|e| e.0 < 3.0).map(|e| e.1).collect();
        close.iter().sum::<f32>() / close.len() as f32
    };
    assert!(
        mean_close(&far) > 2.0 * mean_close(&layered),
        "close up, the far layer alone errs {} radii on average, the table {}",
        mean_close(&far),
        mean_close(&layered)
    );
}
