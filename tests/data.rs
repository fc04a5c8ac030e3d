//! Datasets in BOP layout: the render CLI, the reader, crops, and errors naming the file.

use std::path::Path;
use std::process::Command;

use alignist::cad::{Camera, RenderOptions, Shape, render};
use alignist::data::virtual_crop::{object_box, perspective_crop};
use alignist::data::{BopDataset, symsol_pose};
use alignist::so3::{from_quaternion, geodesic_angle, haar_rotations, to_quaternion};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn train(args: &[&str], out: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_alignist-train"))
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn a_rendered_dataset_reads_back_with_the_same_rotations_and_crops() {
    let dir = tempfile::tempdir().unwrap();
    let rots = haar_rotations(&mut ChaCha8Rng::seed_from_u64(11), 6);
    let csv = dir.path().join("rots.csv");
    let mut text = String::from("qw,qx,qy,qz\n");
    for r in &rots {
        let q = to_quaternion(r);
        text += &format!("{:.17},{:.17},{:.17},{:.17}\n", q[0], q[1], q[2], q[3]);
    }
    std::fs::write(&csv, text).unwrap();
    let root = dir.path().join("cube_ds");
    let out = train(
        &[
            "render",
            "--shape",
            "cube",
            "--size",
            "64",
            "--rotations",
            csv.to_str().unwrap(),
        ],
        &root,
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for f in [
        "models/obj_000001.ply",
        "models/models_info.json",
        "train/000000/rgb/000005.png",
        "train/000000/depth/000005.png",
        "train/000000/mask_visib/000005_000000.png",
        "train/000000/scene_gt.json",
        "train/000000/scene_camera.json",
        "train/000000/scene_gt_equivalents.json",
    ] {
        assert!(root.join(f).exists(), "{f} missing");
    }

    let ds = BopDataset::open(&root, "train").unwrap();
    assert_eq!(ds.samples.len(), 6);
    let mesh = Shape::Cube.mesh();
    let camera = Camera::square(64);
    for (sample, r) in ds.samples.iter().zip(&rots) {
        assert!(geodesic_angle(&sample.rotation, r) < 1e-9);
        assert_eq!(sample.equivalents.len(), 24);
        assert!(
            sample
                .equivalents
                .iter()
                .any(|e| geodesic_angle(e, r) < 1e-9)
        );
        // The equivalents recorded in the file equal those from models_info's symmetries.
        let from_info: Vec<_> = ds.models[&1]
            .symmetry_rotations()
            .unwrap()
            .iter()
            .map(|s| sample.rotation * s)
            .collect();
        for e in &sample.equivalents {
            let best = from_info
                .iter()
                .map(|f| geodesic_angle(e, f))
                .fold(9.0, f64::min);
            assert!(best < 1e-9, "{best}");
        }
        // The crop from disk equals the perspective crop of the same render made in memory, at
        // the box of the projected mesh, and its labels are in that crop's virtual camera.
        let image = render(&mesh, &camera, &symsol_pose(*r), &RenderOptions::default());
        let from_disk = ds.crop(sample, 32).unwrap();
        let bbox = object_box(&mesh, &symsol_pose(*r), &camera);
        let (in_memory, view) =
            perspective_crop(&image.rgb, 64, 64, &sample.cam_k, bbox, 32).unwrap();
        assert_eq!(from_disk.rgb, in_memory);
        assert!(geodesic_angle(&(view.r_ray * from_disk.rotation), r) < 1e-9);
        assert_eq!(from_disk.equivalents.len(), 24);
        // And the object fills the crop's centre.
        let centre = ((16 * 32 + 16) * 3) as usize;
        assert_ne!(&from_disk.rgb[centre..centre + 3], &[0, 0, 0]);
    }
    // The mesh written in millimetres reads back to the NOCS shape.
    let (model, norm) = alignist::cad::Mesh::load(&root.join("models/obj_000001.ply"))
        .unwrap()
        .normalised();
    assert!((norm.scale - 100.0).abs() < 1e-3);
    assert_eq!(model.triangles.len(), mesh.triangles.len());
}

#[test]
fn random_renders_are_seeded_and_cli_errors_are_clear() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a");
    let b = dir.path().join("b");
    for root in [&a, &b] {
        let out = train(
            &[
                "render", "--shape", "tetX", "--count", "3", "--size", "48", "--seed", "7",
            ],
            root,
        );
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let gt =
        |root: &Path| std::fs::read_to_string(root.join("train/000000/scene_gt.json")).unwrap();
    assert_eq!(gt(&a), gt(&b));
    let ds = BopDataset::open(&a, "train").unwrap();
    assert_eq!(ds.samples[0].equivalents.len(), 3);

    let bad_shape = train(
        &["render", "--shape", "pyramid", "--count", "1"],
        &dir.path().join("c"),
    );
    assert!(!bad_shape.status.success());
    assert!(String::from_utf8_lossy(&bad_shape.stderr).contains("unknown shape 'pyramid'"));

    let rots = dir.path().join("bad.csv");
    std::fs::write(&rots, "qw,qx,qy,qz\n1,0,0,0\n0,0,0\n").unwrap();
    let bad_rows = train(
        &[
            "render",
            "--shape",
            "cube",
            "--rotations",
            rots.to_str().unwrap(),
        ],
        &dir.path().join("d"),
    );
    let err = String::from_utf8_lossy(&bad_rows.stderr);
    assert!(!bad_rows.status.success());
    assert!(err.contains("bad.csv") && err.contains("line 3"), "{err}");

    let neither = train(&["render", "--count", "1"], &dir.path().join("e"));
    assert!(!neither.status.success());
}

#[test]
fn corrupt_dataset_files_are_named_in_the_error() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    let out = train(
        &["render", "--shape", "cube", "--count", "2", "--size", "32"],
        &root,
    );
    assert!(out.status.success());
    let gt = root.join("train/000000/scene_gt.json");
    std::fs::write(
        &gt,
        "{\"0\": [{\"cam_R_m2c\": [1,0,0], \"cam_t_m2c\": [0,0,300], \"obj_id\": 1}]}",
    )
    .unwrap();
    let err = BopDataset::open(&root, "train").unwrap_err().to_string();
    assert!(err.contains("scene_gt.json"), "{err}");

    // A rotation that is not a rotation names the image and the field.
    let q = from_quaternion([1.0, 0.0, 0.0, 0.0]).unwrap();
    assert!(geodesic_angle(&q, &q) < 1e-12);
    std::fs::write(
        &gt,
        "{\"0\": [{\"cam_R_m2c\": [2,0,0,0,1,0,0,0,1], \"cam_t_m2c\": [0,0,300], \"obj_id\": 1}]}",
    )
    .unwrap();
    let err = BopDataset::open(&root, "train").unwrap_err().to_string();
    assert!(
        err.contains("scene_gt.json") && err.contains("cam_R_m2c"),
        "{err}"
    );

    assert!(
        BopDataset::open(&root, "test")
            .unwrap_err()
            .to_string()
            .contains("test")
    );
}

#[test]
fn the_perspective_crop_of_an_off_centre_object_is_the_virtual_cameras_view() {
    use alignist::cad::Pose;
    use alignist::data::virtual_crop::{
        box_filter, frame_camera, object_box, perspective_crop, render_crop,
    };
    use nalgebra::Vector3;
    let mesh = Shape::Cube.mesh().normalised().0;
    let camera = frame_camera();
    let rotations = haar_rotations(&mut ChaCha8Rng::seed_from_u64(3), 3);
    // At the centre, mid-way to the corner, and near the edge of the 640×480 frame.
    for ((u, v), r) in [(320.0, 240.0), (480.0, 360.0), (550.0, 395.0)]
        .into_iter()
        .zip(rotations)
    {
        let z = 6.0;
        let pose = Pose {
            rotation: r,
            translation: Vector3::new(
                (u - camera.cx) / camera.fx * z,
                (v - camera.cy) / camera.fy * z,
                z,
            ),
        };
        // The crop cut (warped) out of the full frame, at 128² then 4×-box-filtered…
        let full = render(&mesh, &camera, &pose, &RenderOptions::default());
        let bbox = object_box(&mesh, &pose, &camera);
        let (warped, view) = perspective_crop(
            &full.rgb,
            camera.width,
            camera.height,
            &camera.k(),
            bbox,
            128,
        )
        .unwrap();
        let warped = box_filter(&warped, 128, 4);
        // …and the virtual camera's view rendered directly, 4× supersampled.
        let direct = render_crop(&mesh, &pose, &camera, 32, 4, &RenderOptions::default());
        // The serving path's crop, warped straight to 32² (anti-aliased inside), is close too.
        let (served, _) = perspective_crop(
            &full.rgb,
            camera.width,
            camera.height,
            &camera.k(),
            bbox,
            32,
        )
        .unwrap();
        let served_mad = direct
            .rgb
            .iter()
            .zip(&served)
            .map(|(a, b)| (*a as f64 - *b as f64).abs())
            .sum::<f64>()
            / served.len() as f64;
        assert!(
            served_mad < 3.0,
            "({u}, {v}): served crop differs by {served_mad} grey levels"
        );
        let mad = direct
            .rgb
            .iter()
            .zip(&warped)
            .map(|(a, b)| (*a as f64 - *b as f64).abs())
            .sum::<f64>()
            / warped.len() as f64;
        assert!(
            mad < 2.0,
            "({u}, {v}): mean absolute difference {mad} grey levels"
        );
        let total = |rgb: &[u8]| rgb.iter().map(|&c| c as f64).sum::<f64>();
        assert!(
            total(&direct.rgb) > 0.2 * 255.0 * 32.0 * 32.0,
            "the object fills the crop"
        );
        // The label is the rotation in the virtual camera; R_ray turns it back exactly.
        assert!(geodesic_angle(&(view.r_ray * direct.r_virtual), &r) < 1e-9);
        let off_axis = geodesic_angle(&view.r_ray, &alignist::so3::rot_z(0.0)).to_degrees();
        if u != 320.0 {
            assert!(off_axis > 10.0, "({u}, {v}): ray {off_axis}° off the axis");
        }
    }
}

#[test]
fn virtual_cameras_refuse_boxes_and_intrinsics_without_area() {
    use alignist::data::virtual_crop::VirtualCamera;
    let k = [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0];
    assert!(VirtualCamera::looking_at(&k, [10.0, 10.0, 50.0, 40.0], 64).is_some());
    assert!(VirtualCamera::looking_at(&k, [10.0, 10.0, 0.0, 40.0], 64).is_none());
    assert!(VirtualCamera::looking_at(&k, [10.0, f64::NAN, 5.0, 40.0], 64).is_none());
    let mut bad = k;
    bad[0] = -1.0;
    assert!(VirtualCamera::looking_at(&bad, [10.0, 10.0, 50.0, 40.0], 64).is_none());
}

#[test]
fn frames_with_off_centre_objects_read_back_as_virtual_camera_crops() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("frames");
    let out = train(
        &[
            "render", "--shape", "cube", "--count", "4", "--seed", "5", "--frame", "320x240",
        ],
        &root,
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let info: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(root.join("train/000000/scene_gt_info.json")).unwrap(),
    )
    .unwrap();
    let ds = BopDataset::open(&root, "train").unwrap();
    assert_eq!(ds.samples.len(), 4);
    let mut off_axis = 0;
    for s in &ds.samples {
        let entry = &info[s.im_id.to_string()][0];
        assert_eq!(entry["visib_fract"].as_f64(), Some(1.0), "{entry}");
        let b = s.bbox_obj.expect("bbox_obj read from scene_gt_info.json");
        assert!(b[0] >= 0.0 && b[1] >= 0.0 && b[0] + b[2] <= 320.0 && b[1] + b[3] <= 240.0);
        let crop = ds.crop(s, 32).unwrap();
        // The object fills the crop's centre, and the label turns back to the camera's.
        let centre = (16 * 32 + 16) * 3;
        assert_ne!(&crop.rgb[centre..centre + 3], &[0, 0, 0]);
        let k = s.cam_k;
        let view = alignist::data::virtual_crop::VirtualCamera::looking_at(&k, b, 32).unwrap();
        assert!(geodesic_angle(&(view.r_ray * crop.rotation), &s.rotation) < 1e-9);
        if view.r_ray.angle() > 5f64.to_radians() {
            off_axis += 1;
        }
    }
    assert!(
        off_axis >= 2,
        "the objects are placed away from the optical axis"
    );
    let bad = train(&["render", "--shape", "cube", "--frame", "640by480"], &root);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--frame"));
}

#[test]
fn frame_evaluation_crops_show_the_same_poses_as_the_rendered_ones() {
    use alignist::train::data::FreshRenders;
    let fresh = FreshRenders {
        meshes: vec![Shape::Tetrahedron.mesh().normalised().0],
        supersample: 4,
        pool: None,
        realism: None,
    };
    let names = vec!["tet".to_string()];
    let symmetries = vec![vec![nalgebra::Rotation3::identity()]];
    let rendered = fresh.eval_images(&names, &symmetries, 32, 3, 99);
    let (corrected, uncorrected) = fresh.frame_eval_images(&names, &symmetries, 32, 3, 99);
    assert_eq!((corrected.len(), uncorrected.len()), (3, 3));
    for ((r, c), u) in rendered.iter().zip(&corrected).zip(&uncorrected) {
        // The perspective crop of the whole frame is the rendered crop but for resampling (the
        // detector-style box is rounded out to whole pixels, so the scale differs slightly).
        let mad = r
            .rgb
            .iter()
            .zip(&c.rgb)
            .map(|(a, b)| (*a as f64 - *b as f64).abs())
            .sum::<f64>()
            / r.rgb.len() as f64;
        assert!(mad < 3.0, "{mad}");
        // Corrected labels are the rendered crop's (the virtual camera's) up to the rounding of
        // the box's centre; uncorrected ones are the camera-frame rotation, off by R_ray.
        let a = geodesic_angle(&r.equivalents[0], &c.equivalents[0]).to_degrees();
        assert!(a < 0.5, "{a}°");
        assert_eq!(c.rgb, u.rgb);
    }
}
