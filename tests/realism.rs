//! Realistic renders: smooth shading where the mesh is smooth and hard edges where it is not,
//! highlights that follow the material, occlusion with its visible fraction, crops that are the
//! same for the same seed, train and held-out splits that share no band of any range, and
//! detector boxes that stay in the frame.

use alignist::cad::{
    Camera, CornerNormals, Light, Lighting, Material, Pose, SceneObject, SceneRaster, Shape,
    render_scene,
};
use alignist::data::realism::{
    Neutral, Realism, SceneAssets, Split, background, jitter_box, random_lighting, random_material,
    realistic_crop,
};
use nalgebra::{Rotation3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn at(z: f64, x: f64) -> Pose {
    Pose {
        rotation: Rotation3::from_euler_angles(0.4, 0.7, 0.2),
        translation: Vector3::new(x, 0.0, z),
    }
}

fn one_light() -> Lighting {
    Lighting {
        lights: vec![Light {
            direction: Vector3::new(0.3, -0.4, -1.0).normalize(),
            radiance: [1.0; 3],
        }],
        ambient: [0.1; 3],
    }
}

#[test]
fn corner_normals_are_smooth_on_curved_surfaces_and_hard_on_edges() {
    let cube = Shape::Cube.mesh();
    let normals = CornerNormals::new(&cube, 35.0);
    let sphere = alignist::cad::shapes::uv_sphere_mesh(24, 12);
    let smooth = CornerNormals::new(&sphere, 35.0);
    // The cube keeps its edges: every corner's normal is its face's.
    for f in 0..cube.triangles.len() {
        for n in normals.of(f) {
            assert!((n - cube.face_normal(f)).norm() < 1e-5, "face {f}: {n:?}");
        }
    }
    // The sphere is smooth: a corner's normal is the direction of its vertex (the surface's own
    // normal), whichever face it is taken from.
    for (f, t) in sphere.triangles.iter().enumerate() {
        for (n, &i) in smooth.of(f).iter().zip(t) {
            let radial = sphere.vertices[i as usize].normalize();
            assert!(n.dot(&radial) > 0.995, "face {f}: {n:?} against {radial:?}");
        }
    }
    // Rendered, the sphere's shading varies smoothly: neighbouring pixels differ by little.
    let camera = Camera::square(96);
    let render = |mesh, normals| {
        render_scene(
            &[SceneObject {
                mesh,
                normals,
                pose: at(3.5, 0.0),
                material: Material::MATTE,
            }],
            &camera,
            &one_light(),
        )
    };
    // Inside the silhouette (where the surface turns slowly per pixel), the largest step between
    // neighbouring pixels: small when smooth, large across the facets of the same sphere with
    // every edge hard.
    let largest_step = |normals| {
        let scene = render(&sphere, normals);
        let (w, centre, radius) = (96usize, 48.0, 96.0 / (3.5f64 * 3.5 - 1.0).sqrt());
        let mut largest = 0f32;
        for (i, c) in scene.linear.iter().enumerate() {
            let (x, y) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
            if ((x - centre).powi(2) + (y - centre).powi(2)).sqrt() > 0.8 * radius || i % w == w - 1
            {
                continue;
            }
            if let (Some(a), Some(Some(b))) = (c, scene.linear.get(i + 1)) {
                largest = largest.max((a[0] - b[0]).abs());
            }
        }
        largest
    };
    let (round, faceted) = (
        largest_step(&smooth),
        largest_step(&CornerNormals::new(&sphere, 0.5)),
    );
    assert!(round < 0.05, "a facet edge of {round} on the smooth sphere");
    assert!(
        faceted > 2.0 * round,
        "faceted {faceted} against smooth {round}"
    );
}

#[test]
fn a_smooth_metal_shows_a_highlight_that_a_matte_surface_does_not() {
    let sphere = alignist::cad::shapes::uv_sphere_mesh(32, 16);
    let normals = CornerNormals::new(&sphere, 35.0);
    let camera = Camera::square(64);
    let peak = |material| {
        render_scene(
            &[SceneObject {
                mesh: &sphere,
                normals: &normals,
                pose: at(3.0, 0.0),
                material,
            }],
            &camera,
            &one_light(),
        )
        .linear
        .iter()
        .flatten()
        .map(|c| c[1])
        .fold(0f32, f32::max)
    };
    let grey = [0.5f32; 3];
    let matte = peak(Material {
        base: grey,
        roughness: 1.0,
        metalness: 0.0,
    });
    let shiny = peak(Material {
        base: grey,
        roughness: 0.15,
        metalness: 1.0,
    });
    assert!(shiny > 2.0 * matte, "shiny {shiny} against matte {matte}");
}

#[test]
fn an_occluder_hides_part_of_the_subject_and_the_visible_fraction_says_how_much() {
    let cube = Shape::Cube.mesh();
    let normals = CornerNormals::new(&cube, 35.0);
    let camera = Camera::square(128);
    let subject = SceneObject {
        mesh: &cube,
        normals: &normals,
        pose: at(6.0, 0.0),
        material: Material::MATTE,
    };
    let alone = render_scene(&[subject], &camera, &one_light());
    assert_eq!(alone.visible_fraction(), 1.0);
    assert!(alone.subject.mask_area() > 500);
    // The same cube nearer the camera, moved sideways: it hides part of the subject.
    let occluder = SceneObject {
        pose: at(3.0, 0.8),
        ..subject
    };
    let hidden = render_scene(&[subject, occluder], &camera, &one_light());
    let f = hidden.visible_fraction();
    assert!(0.05 < f && f < 0.95, "visible fraction {f}");
    assert_eq!(hidden.unoccluded_pixels, alone.subject.mask_area());
    let ratio = hidden.subject.mask_area() as f64 / alone.subject.mask_area() as f64;
    assert!((f - ratio).abs() < 1e-12);
    // Hidden pixels carry no NOCS of the subject (the experts' visible points come from these).
    let nocs_pixels = hidden
        .subject
        .nocs
        .iter()
        .filter(|p| !p[0].is_nan())
        .count();
    assert_eq!(nocs_pixels, hidden.subject.mask_area());
    // Drawn on a copy of the subject's raster (how a crop tries an occluder at a few places):
    // the same fraction and the same render, and the copy drawn from is untouched.
    let base = SceneRaster::of(&[subject], &camera);
    let mut with = base.clone();
    with.draw(occluder, &camera);
    assert_eq!(with.visible_fraction(), f);
    assert_eq!(base.visible_fraction(), 1.0);
    let shaded = with.shade(&camera, &one_light());
    assert_eq!(shaded.linear, hidden.linear);
    assert_eq!(shaded.subject.mask, hidden.subject.mask);
    assert_eq!(shaded.subject.depth, hidden.subject.depth);
    // Behind the subject, it hides nothing.
    let behind = SceneObject {
        pose: at(12.0, 0.5),
        ..subject
    };
    assert_eq!(
        render_scene(&[subject, behind], &camera, &one_light()).visible_fraction(),
        1.0
    );
}

#[test]
fn realistic_crops_are_deterministic_per_seed_and_vary_between_seeds() {
    let meshes = vec![Shape::Cube.mesh(), Shape::Cone.mesh()];
    let assets = SceneAssets::new(&meshes, Realism::TRAIN);
    let crop =
        |object, seed| realistic_crop(&assets, object, 32, 2, &mut ChaCha8Rng::seed_from_u64(seed));
    let (a, b) = (crop(1, 7), crop(1, 7));
    assert_eq!(a.rgb, b.rgb);
    assert_eq!(a.r_virtual, b.r_virtual);
    assert_eq!(a.render.mask, b.render.mask);
    assert_eq!(a.rgb.len(), 32 * 32 * 3);
    let c = crop(1, 8);
    assert_ne!(a.rgb, c.rgb);
    // Every crop shows its object: visible pixels with NOCS, at least half not hidden by
    // another object (the frame's edge may cut more).
    for seed in 0..40 {
        let r = crop((seed % 2) as usize, seed);
        assert!(r.render.mask_area() >= 4, "seed {seed}");
        assert!(
            r.visible_fraction > 0.0 && r.visible_fraction <= 1.0,
            "seed {seed}: {}",
            r.visible_fraction
        );
        // Backgrounds are not black: the image is not the object on nothing.
        let lit = r
            .rgb
            .chunks(3)
            .filter(|p| p.iter().any(|&v| v > 12))
            .count();
        assert!(lit > 32 * 32 / 2, "seed {seed}: {lit} lit pixels");
    }
}

#[test]
fn a_factor_held_neutral_keeps_each_crops_pose_and_changes_only_that_factor() {
    // A mesh of no colours of its own, as a user's scan (the shapes are bluish grey).
    let mut cube = Shape::Cube.mesh();
    cube.colors = None;
    let meshes = vec![cube, Shape::Cone.mesh()];
    let base = Realism {
        clutter: 0.0,
        ..Realism::HELD_OUT
    };
    let crop = |neutral, seed| {
        let assets = SceneAssets::new(&meshes, Realism { neutral, ..base });
        realistic_crop(&assets, 0, 32, 2, &mut ChaCha8Rng::seed_from_u64(seed))
    };
    let all = Neutral {
        material: true,
        lighting: true,
        background: true,
        camera: true,
    };
    let background = Neutral {
        background: true,
        ..Neutral::NONE
    };
    for seed in 0..12 {
        let varied = crop(Neutral::NONE, seed);
        let (plain, black) = (crop(all, seed), crop(background, seed));
        // Same pose and the same pixels of the object in every variant.
        for other in [&plain, &black] {
            assert_eq!(other.r_virtual, varied.r_virtual, "seed {seed}");
            assert_eq!(other.render.mask, varied.render.mask, "seed {seed}");
        }
        assert_ne!(plain.rgb, varied.rgb, "seed {seed}");
        // Everything neutral: a grey object under white light on black, no noise.
        let ss = plain.render.width as usize / 32;
        let mut object = 0;
        for (p, rgb) in plain.rgb.chunks(3).enumerate() {
            let (x, y) = (p % 32, p / 32);
            let covered = (0..ss * ss)
                .filter(|q| {
                    let (bx, by) = (x * ss + q % ss, y * ss + q / ss);
                    plain.render.mask[by * plain.render.width as usize + bx]
                })
                .count();
            assert!(rgb[0] == rgb[1] && rgb[1] == rgb[2], "seed {seed}: {rgb:?}");
            if covered == 0 {
                assert_eq!(rgb, [0, 0, 0], "seed {seed}: background at {x}, {y}");
            } else if covered == ss * ss {
                object += 1;
                assert!(rgb[0] > 0, "seed {seed}: an object pixel is black");
            }
        }
        assert!(object > 0, "seed {seed}");
    }
}

#[test]
fn train_and_held_out_splits_draw_from_disjoint_bands() {
    // Roughness bands: [0.08, 1] in six bands; training takes the even ones, held-out the odd.
    let band = |r: f32| ((r as f64 - 0.08) / ((1.0 - 0.08) / 6.0)).floor() as i64;
    for seed in 0..200 {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let train = random_material(&mut rng, Split::Train, false);
        let held = random_material(&mut rng, Split::HeldOut, false);
        assert_eq!(band(train.roughness) % 2, 0, "{train:?}");
        assert_eq!(band(held.roughness) % 2, 1, "{held:?}");
        let lights = random_lighting(&mut rng, Split::Train);
        assert!((1..=3).contains(&lights.lights.len()));
    }
    // The splits by the names the probes take.
    assert_eq!("train".parse::<Split>(), Ok(Split::Train));
    assert_eq!("held-out".parse::<Split>(), Ok(Split::HeldOut));
    let err = "heldout".parse::<Split>().unwrap_err();
    assert!(err.contains("heldout"), "{err}");
    // Each split has its own photographs, all decoded.
    let (train, held) = (
        alignist::data::realism::photos(Split::Train),
        alignist::data::realism::photos(Split::HeldOut),
    );
    assert_eq!((train.len(), held.len()), (5, 4));
    assert!(
        train
            .iter()
            .all(|t| held.iter().all(|h| t.as_raw() != h.as_raw()))
    );
    // Backgrounds of either split fill the image with finite colours.
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for split in [Split::Train, Split::HeldOut] {
        for _ in 0..12 {
            let bg = background(&mut rng, split, 48);
            assert_eq!(bg.len(), 48 * 48);
            assert!(bg.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
        }
    }
}

#[test]
fn detector_boxes_err_around_the_true_box_and_stay_in_the_frame() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let exact = [600.0, 100.0, 60.0, 40.0];
    let mut moved = 0;
    for _ in 0..500 {
        let b = jitter_box(&mut rng, exact, 0.08, 640, 480);
        assert!(
            b[0] >= 0.0 && b[1] >= 0.0 && b[2] >= 2.0 && b[3] >= 2.0,
            "{b:?}"
        );
        assert!(
            b[0] + b[2] <= 640.0 + 1e-9 && b[1] + b[3] <= 480.0 + 1e-9,
            "{b:?}"
        );
        if (b[0] - exact[0]).abs() > 0.5 {
            moved += 1;
        }
    }
    assert!(moved > 400, "{moved} of 500 boxes moved");
    // Without error, a box inside the frame stays as it is; one past the edge is clipped.
    let inside = [500.0, 100.0, 60.0, 40.0];
    assert_eq!(jitter_box(&mut rng, inside, 0.0, 640, 480), inside);
    assert_eq!(
        jitter_box(&mut rng, exact, 0.0, 640, 480),
        [600.0, 100.0, 40.0, 40.0]
    );
}

#[test]
fn a_textured_obj_renders_its_texture() {
    // A 2 × 2 quad facing the camera, its texture a 4 × 4 PNG of four 2 × 2 blocks: red top left,
    // green top right, blue bottom left, yellow bottom right (image rows down, OBJ's v up).
    let dir = tempfile::tempdir().unwrap();
    let texture = image::RgbImage::from_fn(4, 4, |x, y| {
        image::Rgb(match (x < 2, y < 2) {
            (true, true) => [255, 0, 0],
            (false, true) => [0, 255, 0],
            (true, false) => [0, 0, 255],
            (false, false) => [255, 255, 0],
        })
    });
    texture.save(dir.path().join("blocks.png")).unwrap();
    std::fs::write(
        dir.path().join("quad.mtl"),
        "newmtl blocks\nKd 1 1 1\nmap_Kd blocks.png\n",
    )
    .unwrap();
    std::fs::write(
        dir.path().join("quad.obj"),
        "mtllib quad.mtl\nv -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n\
         vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl blocks\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n",
    )
    .unwrap();
    let mesh = alignist::cad::Mesh::load(&dir.path().join("quad.obj")).unwrap();
    assert!(matches!(
        mesh.colors,
        Some(alignist::cad::MeshColors::Texture(_))
    ));
    let normals = CornerNormals::new(&mesh, 35.0);
    let scene = render_scene(
        &[SceneObject {
            mesh: &mesh,
            normals: &normals,
            pose: Pose {
                rotation: Rotation3::identity(),
                translation: Vector3::new(0.0, 0.0, 3.0),
            },
            material: Material::MATTE,
        }],
        &Camera::square(96),
        // Ambient light only: a pixel's colour is the albedo, the texel's colour made linear.
        &Lighting {
            lights: Vec::new(),
            ambient: [1.0; 3],
        },
    );
    // Object (x, y) is seen at pixel (48 + 32x, 48 + 32y) (camera y points down): the texel
    // of uv (0.25, 0.75) (red) at object (−0.5, 0.5), and so on.
    let at = |u: usize, v: usize| scene.linear[v * 96 + u].expect("on the quad");
    for ((u, v), want) in [
        ((32, 64), [1.0, 0.0, 0.0]),
        ((64, 64), [0.0, 1.0, 0.0]),
        ((32, 32), [0.0, 0.0, 1.0]),
        ((64, 32), [1.0, 1.0, 0.0]),
    ] {
        let got = at(u, v);
        for k in 0..3 {
            assert!(
                (got[k] - want[k]).abs() < 1e-3,
                "pixel ({u}, {v}): {got:?}, want {want:?}"
            );
        }
    }
    // Written to PLY (a bundle's mesh), the texture is kept as the colours at the vertices.
    let ply = dir.path().join("quad.ply");
    alignist::cad::write_ply(&mesh, &ply).unwrap();
    let back = alignist::cad::Mesh::load(&ply).unwrap();
    assert!(matches!(
        back.colors,
        Some(alignist::cad::MeshColors::PerVertex(_))
    ));
}

#[test]
fn a_plain_share_given_to_a_training_image_replaces_the_realisms() {
    use alignist::train::data::FreshRenders;
    let meshes = vec![Shape::Cube.mesh()];
    let fresh = FreshRenders {
        meshes: meshes.clone(),
        supersample: 2,
        pool: None,
        realism: Some(SceneAssets::new(&meshes, Realism::TRAIN)),
    };
    // A plain crop is the part on black around its exact box: its four corners are black. A
    // realistic one has a background there (the frame's edge may cut off one side, not all).
    let plain_corners = |rgb: &[u8]| {
        [0, 31, 32 * 31, 32 * 32 - 1]
            .iter()
            .all(|&i| rgb[3 * i..3 * i + 3] == [0, 0, 0])
    };
    let crops = |plain| {
        (0..12)
            .map(|seed| {
                let im = fresh.training_image(0, 32, plain, &mut ChaCha8Rng::seed_from_u64(seed));
                plain_corners(&im.rgb)
            })
            .collect::<Vec<_>>()
    };
    assert!(crops(Some(1.0)).iter().all(|&g| g));
    assert!(crops(Some(0.0)).iter().all(|&g| !g));
    // Without one, the realism's own share (1/10): mostly realistic.
    let plain = crops(None).iter().filter(|&&g| g).count();
    assert!(plain <= 4, "{plain} of 12 plain");
}

#[test]
fn the_plain_share_is_annealed_from_its_start_to_the_realisms() {
    use alignist::train::TrainConfig;
    let end = Realism::TRAIN.plain;
    let fixed = TrainConfig::default();
    assert_eq!(fixed.plain_share(0, 100, end), end);
    assert_eq!(fixed.plain_share(99, 100, end), end);
    let curriculum = TrainConfig {
        plain_start: Some(1.0),
        pretrained: None,
        pretrained_file: None,
        encoder_lr_scale: None,
        contrast: None,
        target_temperature: None,
        ..TrainConfig::default()
    };
    assert_eq!(curriculum.plain_share(0, 101, end), 1.0);
    assert!((curriculum.plain_share(50, 101, end) - (1.0 + end) / 2.0).abs() < 1e-12);
    assert!((curriculum.plain_share(100, 101, end) - end).abs() < 1e-12);
    assert!((curriculum.plain_share(500, 101, end) - end).abs() < 1e-12);
}
