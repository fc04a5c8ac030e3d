//! The network's parts: encoder and head shapes, the losses' values and gradients.

use alignist::encoding::RotationEncoding;
use alignist::net::{
    EncoderConfig, HeadConfig, Precision, ResNetLayout, gkl_loss, ipdf_loss, l1_measure_loss,
};
use burn::tensor::{Device, Distribution, Tensor, TensorData};

fn device() -> Device {
    alignist::backend::device()
}

fn t2(values: Vec<f32>, shape: [usize; 2], device: &Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(values, shape), device)
}

fn scalar(t: Tensor<1>) -> f64 {
    t.into_scalar::<f32>() as f64
}

#[test]
fn gkl_is_zero_at_the_target_and_positive_elsewhere() {
    let d = device();
    let log_a = t2(vec![-3.0, -0.5, 0.0, -10.0, 1.0, -2.0], [2, 3], &d);
    assert!(scalar(gkl_loss(log_a.clone(), log_a.clone())).abs() < 1e-5);
    for shift in [-1.0f32, -0.1, 0.1, 2.0] {
        let s = log_a.clone().add_scalar(shift);
        let v = scalar(gkl_loss(log_a.clone(), s));
        assert!(v > 1e-4, "shift {shift}: {v}");
    }
    // A single wrong entry is enough.
    let mut bent = vec![-3.0, -0.5, 0.0, -10.0, 1.0, -2.0];
    bent[4] = 0.5;
    assert!(scalar(gkl_loss(log_a.clone(), t2(bent, [2, 3], &d))) > 1e-3);
    assert!(scalar(l1_measure_loss(log_a.clone(), log_a.clone())).abs() < 1e-6);
}

#[test]
fn gkl_gradient_matches_finite_differences() {
    let plain = device();
    let ad = plain.clone().autodiff();
    let log_a = vec![-1.0f32, -0.2, -3.0, 0.4];
    let s0 = vec![-0.5f32, 0.1, -2.0, 0.0];
    let s = t2(s0.clone(), [1, 4], &ad).require_grad();
    let loss = gkl_loss(t2(log_a.clone(), [1, 4], &ad), s.clone());
    let grads = loss.backward();
    let g: Vec<f32> = s
        .grad(&grads)
        .unwrap()
        .into_data()
        .try_to_vec::<f32>()
        .unwrap();
    let f = |s: &[f32]| -> f64 {
        log_a
            .iter()
            .zip(s)
            .map(|(&la, &sk)| {
                let (la, sk) = (la as f64, sk as f64);
                la.exp() * (la - sk) + sk.exp() - la.exp()
            })
            .sum()
    };
    for k in 0..4 {
        let h = 1e-3f32;
        let mut up = s0.clone();
        up[k] += h;
        let mut down = s0.clone();
        down[k] -= h;
        let numeric = (f(&up) - f(&down)) / (2.0 * h as f64);
        // Analytic: exp(s) − a.
        let analytic = (s0[k] as f64).exp() - (log_a[k] as f64).exp();
        assert!(
            (numeric - analytic).abs() < 1e-3,
            "{k}: {numeric} vs {analytic}"
        );
        assert!(
            (g[k] as f64 - numeric).abs() < 1e-3,
            "{k}: autodiff {} vs numeric {numeric}",
            g[k]
        );
    }
}

#[test]
fn ipdf_loss_is_the_negative_log_softmax_of_column_zero() {
    let d = device();
    let s = vec![2.0f32, 0.0, -1.0, 0.5, 0.5, 0.5];
    let v = scalar(ipdf_loss(t2(s.clone(), [2, 3], &d)));
    let row = |r: &[f32]| {
        let z: f64 = r.iter().map(|&x| (x as f64).exp()).sum();
        -(r[0] as f64) + z.ln()
    };
    let expected = (row(&s[..3]) + row(&s[3..])) / 2.0;
    assert!((v - expected).abs() < 1e-5, "{v} vs {expected}");
}

#[test]
fn encoder_and_head_give_one_score_per_image_and_rotation() {
    let d = alignist::backend::device_for(alignist::backend::Workload::Conv);
    let encoder = EncoderConfig::new(ResNetLayout::Tiny).init(&d);
    let images: Tensor<4> = Tensor::random([2, 3, 64, 64], Distribution::Default, &d);
    let features = encoder.forward(images);
    assert_eq!(features.dims(), [2, ResNetLayout::Tiny.feature_dim()]);
    let enc = RotationEncoding::Cube;
    let head = HeadConfig::new(ResNetLayout::Tiny.feature_dim(), enc.dim()).init(&d);
    let grid = alignist::so3::GridLevel::new(0).unwrap().matrices_f32();
    let rotations = enc.encode_tensor(&grid, &d);
    // Per-image rotation sets [B, K, E].
    let per_image = Tensor::cat(
        vec![
            rotations.clone().unsqueeze::<3>(),
            rotations.clone().unsqueeze::<3>(),
        ],
        0,
    );
    let scores = head.forward(features.clone(), per_image);
    assert_eq!(scores.shape.dims(), [2, 72]);
    assert_eq!(scores.feature.dims(), [2, 72]);
    // Precomputed rotation projections shared by every image give the same scores.
    let shared = head.project_rotations(rotations).unsqueeze::<3>();
    let again = head.forward_projected(features, shared);
    let a: Vec<f32> = scores.combined().into_data().try_to_vec::<f32>().unwrap();
    let b: Vec<f32> = again.combined().into_data().try_to_vec::<f32>().unwrap();
    for (x, y) in a.iter().zip(&b) {
        assert!((x - y).abs() < 1e-4);
    }
    assert_eq!(ResNetLayout::Resnet18.feature_dim(), 512);
    assert_eq!(ResNetLayout::Resnet50.feature_dim(), 2048);
}

#[test]
fn a_grown_encoder_computes_the_same_features_with_more_blocks_and_channels() {
    use burn::module::Module;
    let d = alignist::backend::device_for(alignist::backend::Workload::Conv);
    let tiny = EncoderConfig::new(ResNetLayout::Tiny).init(&d);
    let images: Tensor<4> = Tensor::random([3, 3, 24, 24], Distribution::Default, &d);
    let values = |t: Tensor<2>| t.into_data().try_to_vec::<f32>().unwrap();
    let before = values(tiny.clone().valid().forward(images.clone()));
    let close = |a: &[f32], b: &[f32]| {
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= 1e-5 * x.abs().max(1.0), "{x} != {y}");
        }
    };
    let deep = tiny
        .clone()
        .grown(ResNetLayout::Tiny, ResNetLayout::TinyDeep, &d)
        .expect("tiny_deep grows tiny");
    let fresh = |layout| EncoderConfig::new(layout).init(&d).num_params();
    assert_eq!(deep.num_params(), fresh(ResNetLayout::TinyDeep));
    assert!(deep.num_params() > fresh(ResNetLayout::Tiny));
    let after = values(deep.clone().valid().forward(images.clone()));
    assert_eq!(before.len(), after.len());
    close(&before, &after);
    // Wider: the old 128 features first and unchanged, 64 more after them.
    for (from, encoder) in [(ResNetLayout::Tiny, tiny), (ResNetLayout::TinyDeep, deep)] {
        let wide = encoder
            .grown(from, ResNetLayout::TinyWide, &d)
            .expect("tiny_wide grows tiny and tiny_deep");
        assert_eq!(wide.num_params(), fresh(ResNetLayout::TinyWide));
        let after = values(wide.valid().forward(images.clone()));
        assert_eq!(after.len(), 3 * 192);
        for (image, features) in after.chunks(192).enumerate() {
            close(&before[image * 128..(image + 1) * 128], &features[..128]);
            // The added channels are not dead: their own weights are fresh.
            assert!(features[128..].iter().any(|&f| f > 0.0), "{from:?}");
        }
    }
    // Only the same stem and block kind with no fewer channels or blocks per stage grow.
    assert!(ResNetLayout::TinyDeep.grows(ResNetLayout::Tiny));
    assert!(ResNetLayout::TinyWide.grows(ResNetLayout::TinyDeep));
    assert!(ResNetLayout::Tiny.grows(ResNetLayout::Tiny));
    assert!(!ResNetLayout::Tiny.grows(ResNetLayout::TinyDeep));
    assert!(!ResNetLayout::TinyDeep.grows(ResNetLayout::TinyWide));
    assert!(!ResNetLayout::Resnet18.grows(ResNetLayout::Tiny));
    assert!(!ResNetLayout::Resnet50.grows(ResNetLayout::Resnet18));
    let tiny = EncoderConfig::new(ResNetLayout::Tiny).init(&d);
    assert!(
        tiny.grown(ResNetLayout::Tiny, ResNetLayout::Resnet18, &d)
            .is_none()
    );
}

/// A head widened for a grown encoder's added features scores as before while they are zero
/// (they are not yet read), and reads them once the added rows are trained.
#[test]
fn a_head_for_more_features_scores_the_same_on_the_old_ones() {
    let d = device();
    let enc = RotationEncoding::Cube;
    let head = HeadConfig::new(16, enc.dim()).init(&d);
    let grid = alignist::so3::GridLevel::new(0).unwrap().matrices_f32();
    let shared = head
        .project_rotations(enc.encode_tensor(&grid, &d))
        .unsqueeze::<3>();
    let features: Tensor<2> = Tensor::random([2, 16], Distribution::Default, &d);
    let scores = |h: &alignist::net::DualHead, f: Tensor<2>| -> Vec<f32> {
        h.forward_projected(f, shared.clone())
            .combined()
            .into_data()
            .try_to_vec::<f32>()
            .unwrap()
    };
    let before = scores(&head, features.clone());
    let wide = head.clone().with_image_features(24);
    let more: Tensor<2> = Tensor::random([2, 8], Distribution::Default, &d);
    let after = scores(&wide, Tensor::cat(vec![features.clone(), more], 1));
    assert_eq!(before, after);
    // Fewer features than it reads: unchanged.
    assert_eq!(scores(&head.with_image_features(8), features), before);
}

#[test]
fn an_output_scale_multiplies_the_combined_log_density() {
    let d = device();
    let enc = RotationEncoding::Cube;
    let head = HeadConfig::new(16, enc.dim()).init(&d);
    let features: Tensor<2> = Tensor::random([2, 16], Distribution::Default, &d);
    let grid = alignist::so3::GridLevel::new(0).unwrap().matrices_f32();
    let shared = head
        .project_rotations(enc.encode_tensor(&grid, &d))
        .unsqueeze::<3>();
    let scores = |h: &alignist::net::DualHead| -> Vec<f32> {
        h.forward_projected(features.clone(), shared.clone())
            .combined()
            .into_data()
            .try_to_vec::<f32>()
            .unwrap()
    };
    let before = scores(&head);
    let after = scores(&head.clone().with_output_scale(0.25));
    assert!(before.iter().any(|v| v.abs() > 1e-3));
    for (a, b) in before.iter().zip(&after) {
        assert!((0.25 * a - b).abs() < 1e-5, "{a} × 0.25 ≠ {b}");
    }
}

/// `rows` rotations spread over SO(3) (row-major), shifted by `offset` about the first axis.
fn spread_rotations(rows: usize, offset: f64) -> Vec<[f32; 9]> {
    (0..rows)
        .map(|i| {
            let m = nalgebra::UnitQuaternion::from_euler_angles(
                0.37 * i as f64 + offset,
                1.3 * (i as f64 * 0.11).sin(),
                -0.7 * i as f64,
            )
            .to_rotation_matrix();
            std::array::from_fn(|j| m.matrix()[(j / 3, j % 3)] as f32)
        })
        .collect()
}

/// The fused inference head against the burn head it is read from, on each set of kernels (the
/// widest this core has, AVX2, matrixmultiply): both branches, for row counts around the
/// kernels' row blocks (6, 12) and the tile size (odd, one under, at and over a tile boundary,
/// several tiles).
fn assert_fused_matches(
    head: &alignist::net::DualHead,
    image_dim: usize,
    encoding: &RotationEncoding,
    d: &Device,
) {
    use alignist::net::{FusedHead, Kernels, Rows};
    for kernels in [Kernels::Widest, Kernels::Avx2, Kernels::Portable] {
        let fused = FusedHead::with_kernels(head, kernels);
        eprintln!("{kernels}: {}", fused.kernel_paths());
        assert_fused_matches_on(&fused, head, image_dim, encoding, d);
        // From encodings (the finer levels of a search), the kernels project inside the tiles.
        let rotations = spread_rotations(300, 0.5);
        let enc = encoding.encode(&rotations);
        let features: Vec<f32> = (0..image_dim).map(|i| (i % 5) as f32 / 5.0).collect();
        let image = fused.image_term(&features);
        let projected = fused.branch_scores(&image, &fused.project_rotations(&enc));
        let encoded = fused.branch_scores_in(Precision::F32, &image, Rows::Encoded(&enc));
        for (p, e) in projected.0.iter().zip(&encoded.0) {
            assert!(
                (p - e).abs() <= 1e-4 * p.abs().max(1.0),
                "{kernels}: {p} against {e}"
            );
        }
    }
}

/// [`assert_fused_matches`] for one set of kernels.
fn assert_fused_matches_on(
    fused: &alignist::net::FusedHead,
    head: &alignist::net::DualHead,
    image_dim: usize,
    encoding: &RotationEncoding,
    d: &Device,
) {
    let tile = alignist::net::tiles::tile_rows();
    for (case, rows) in [
        1,
        7,
        11,
        12,
        13,
        tile - 1,
        tile,
        tile + 1,
        2 * tile + 3,
        1001,
    ]
    .into_iter()
    .enumerate()
    {
        let rotations = spread_rotations(rows, case as f64);
        let features: Vec<f32> = (0..image_dim)
            .map(|i| ((i * 37 + case * 11) % 17) as f32 / 17.0)
            .collect();
        let enc = encoding.encode(&rotations);
        let reference = head.forward(
            t2(features.clone(), [1, image_dim], d),
            encoding
                .encode_tensor(&rotations, d)
                .reshape([1, rows, encoding.dim()]),
        );
        let read = |t: Tensor<2>| t.into_data().try_to_vec::<f32>().unwrap();
        let (shape, feature) = (read(reference.shape), read(reference.feature));
        let (fs, ff) =
            fused.branch_scores(&fused.image_term(&features), &fused.project_rotations(&enc));
        assert_eq!((fs.len(), ff.len()), (rows, rows));
        for (name, got, want) in [("shape", &fs, &shape), ("feature", &ff, &feature)] {
            let scale = want.iter().map(|v| v.abs()).sum::<f32>() / rows as f32;
            for (i, (g, w)) in got.iter().zip(want.iter()).enumerate() {
                assert!(
                    (g - w).abs() <= 1e-4 * w.abs().max(scale),
                    "{} {name} branch, {rows} rows, row {i}: fused {g} against burn {w}",
                    fused.kernel_paths()
                );
            }
        }
    }
}

#[test]
fn the_fused_head_gives_the_burn_heads_scores() {
    let d = device();
    let encoding = RotationEncoding::Cube;
    let head = HeadConfig::new(32, encoding.dim())
        .with_hidden(64)
        .with_layers(4)
        .init(&d)
        .with_output_biases(-2.5, 1.5);
    assert_fused_matches(&head, 32, &encoding, &d);
    // The shipped bundle's trained head.
    let bundle = alignist::bundle::model::ModelBundle::load(std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/models/symsol1"
    )))
    .unwrap();
    let network = &bundle.manifest.network;
    assert_fused_matches(
        &bundle.network.head,
        network.layout.feature_dim(),
        &network.encoding,
        &alignist::backend::device_for(alignist::backend::Workload::Conv),
    );
}

/// The default coarse-to-fine search finds the maximum of the exhaustive grid (level 3) on
/// fresh renders of the shipped model's five shapes: its top-1 scores as high as the best of all
/// 36 864 cells (on symmetric shapes an equivalent cell may tie) on every image.
#[test]
fn the_default_search_finds_the_exhaustive_maximum_at_level_3() {
    use alignist::engine::{Engine, EngineConfig, PredictOptions};
    let path = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/models/symsol1"));
    let bundle = alignist::bundle::model::ModelBundle::load(path).unwrap();
    let images = alignist::train::data::BundleRenders::of(&bundle, 2).eval_images(
        bundle.manifest.network.image_size,
        4,
        7,
    );
    let model = Engine::load_model(path, EngineConfig::default()).unwrap();
    let options = PredictOptions {
        top_k: 5,
        level: Some(3),
        mode_angle_deg: None,
        ..Default::default()
    };
    for (i, im) in images.iter().enumerate() {
        let features = model
            .features(&[&im.rgb])
            .expect("crops of the input side")
            .swap_remove(0);
        let logits = model.logits_at(&features, 3).unwrap();
        let best = logits.iter().copied().fold(f32::MIN, f32::max);
        let top = model.predict(&features, &options, None).unwrap().top[0].cell;
        let gap = best - logits[top as usize];
        assert!(
            gap >= -1e-4,
            "image {i}: the search scored above the grid's best"
        );
        // The search shipped before (128 cells at every level, f32) stopped on another of the
        // icosahedron's 60 equivalent modes on all 4 icosahedra (0.017 to 0.131 nats below);
        // the default since (1024 cells of level 2, coarse levels in bfloat16) finds the best
        // cell on every image.
        assert!(
            gap <= 1e-3,
            "image {i} ({}): {gap} nats below the best",
            im.object
        );
    }
}

/// A refined level of the search at or below the full levels scores its cells from the level's
/// projections, precomputed at load: the gathered cells' scores are the full level's at those
/// cells in every precision, and in f32 those of the cells' rotations encoded, to rounding.
#[test]
fn a_full_levels_cells_score_from_its_projections_as_from_their_rotations() {
    use alignist::engine::{Engine, EngineConfig};
    use alignist::net::Branches;
    let path = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/models/symsol1"));
    let bundle = alignist::bundle::model::ModelBundle::load(path).unwrap();
    let image = alignist::train::data::BundleRenders::of(&bundle, 2)
        .eval_images(bundle.manifest.network.image_size, 1, 5)
        .swap_remove(0);
    let model = Engine::load_model(path, EngineConfig::default()).unwrap();
    let features = model.features(&[&image.rgb]).unwrap();
    let projected = model.projected(3).expect("level 3 is a full level");
    let cells: Vec<u64> = (0..1000u64)
        .map(|i| i * 37 % projected.grid.len() as u64)
        .collect();
    for precision in [
        Precision::F32,
        Precision::Bf16,
        Precision::F16,
        Precision::I8,
    ] {
        for branches in [Branches::Both, Branches::Shape] {
            let all = projected.log_weights_of_row_by(precision, branches, &features[0]);
            let some = projected.log_weights_of_cells_by(precision, branches, &features[0], &cells);
            assert_eq!(some.len(), cells.len());
            for (&c, s) in cells.iter().zip(&some) {
                let full = all[c as usize];
                assert!(
                    (full - s).abs() <= 1e-5 * full.abs().max(1.0),
                    "{precision} {branches:?} cell {c}: {s} gathered, {full} in full"
                );
            }
        }
    }
    let grid = model.grid(3).unwrap();
    let rotations: Vec<[f32; 9]> = cells
        .iter()
        .map(|&c| alignist::so3::to_row_major_f32(&grid.rotation(c)))
        .collect();
    let encoded = model.score_rotations_many(&features, &[rotations], Precision::F32);
    let gathered =
        projected.log_weights_of_cells_by(Precision::F32, Branches::Both, &features[0], &cells);
    for ((&c, e), g) in cells.iter().zip(&encoded[0]).zip(&gathered) {
        assert!((e - g).abs() <= 1e-3, "cell {c}: {g} gathered, {e} encoded");
    }
}

/// A bundle is served up to the grid levels its manifest sets, never above: the shipped one,
/// its manifest set to search level 5, is refused a level-6 search by an engine allowing 6.
/// Without a cap (what the trainer writes) the server's own settings decide.
#[test]
fn the_manifests_levels_cap_what_the_engine_serves() {
    use alignist::engine::{Engine, EngineConfig, EngineError, PredictOptions};
    // The shipped bundle, its manifest recording lower levels than the engine's defaults.
    let shipped = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/models/symsol1"));
    let dir = tempfile::tempdir().unwrap();
    let path = &dir.path().join("symsol1");
    alignist::bundle::model::copy_dir(shipped, path).unwrap();
    let manifest_path = path.join("manifest.json");
    let mut manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&manifest_path).unwrap()).unwrap();
    let config = EngineConfig::default();
    manifest.as_object_mut().unwrap().remove("levels");
    std::fs::write(&manifest_path, manifest.to_string()).unwrap();
    let uncapped = Engine::load_model(path, config).unwrap();
    assert_eq!(uncapped.config().search_max_level, config.search_max_level);
    assert_eq!(uncapped.config().max_full_level, config.max_full_level);
    manifest["levels"] = serde_json::json!({ "full_max": 3, "search_max": 5 });
    std::fs::write(&manifest_path, manifest.to_string()).unwrap();
    let levels = alignist::bundle::model::ModelBundle::load(path)
        .unwrap()
        .manifest
        .levels
        .unwrap();
    assert!(config.search_max_level > levels.search_max, "{levels:?}");
    let model = Engine::load_model(path, config).unwrap();
    assert_eq!(model.config().search_max_level, levels.search_max);
    assert_eq!(model.config().max_full_level, levels.full_max);
    let side = model.input_size() as usize;
    let features = model
        .features(&[&vec![128u8; side * side * 3]])
        .expect("crops of the input side")
        .swap_remove(0);
    let above = PredictOptions {
        top_k: 1,
        level: Some(levels.search_max + 1),
        mode_angle_deg: None,
        ..Default::default()
    };
    assert!(matches!(
        model.predict(&features, &above, None),
        Err(EngineError::InvalidArgument { .. })
    ));
}

/// A crop of another side than the model's (a library caller that skipped `Model::prepare`) is
/// refused by name; the encoder used to panic on its shape.
#[test]
fn crops_of_another_side_are_refused_by_name() {
    use alignist::engine::{Engine, EngineConfig, EngineError};
    let path = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/models/symsol1"));
    let model = Engine::load_model(path, EngineConfig::default()).unwrap();
    let side = model.input_size() as usize;
    let small = vec![128u8; 32 * 32 * 3];
    match model.features(&[&vec![128u8; side * side * 3], &small]) {
        Err(EngineError::InvalidArgument { field, message }) => {
            assert_eq!(field, "crops[1]");
            assert!(message.contains(&format!("{side}×{side}")), "{message}");
        }
        other => panic!("expected InvalidArgument, got {:?}", other.map(|f| f.len())),
    }
    assert!(model.features(&[]).unwrap().is_empty());
}

#[test]
fn kernel_names_round_trip_and_bad_ones_are_refused() {
    use alignist::net::Kernels;
    for k in [
        Kernels::Widest,
        Kernels::Avx512,
        Kernels::Avx2,
        Kernels::Portable,
    ] {
        assert_eq!(k.name().parse::<Kernels>(), Ok(k));
    }
    let err = "avx1024".parse::<Kernels>().unwrap_err();
    assert!(err.contains("avx1024") && err.contains("portable"), "{err}");
}

#[test]
fn bf16_rounding_is_to_the_nearest_even() {
    use alignist::net::bf16::{from_bf16, round_bf16, to_bf16};
    assert_eq!(to_bf16(1.0), 0x3f80);
    assert_eq!(to_bf16(-2.0), 0xc000);
    assert_eq!(from_bf16(0x3f80), 1.0);
    // 1 + 2⁻⁸ lies halfway between 1 and 1 + 2⁻⁷: ties go to the even one (1); just above, up.
    assert_eq!(round_bf16(1.0 + 1.0 / 256.0), 1.0);
    assert_eq!(
        round_bf16(1.0 + 1.0 / 256.0 + 1.0 / 65536.0),
        1.0 + 1.0 / 128.0
    );
    // 1 + 3·2⁻⁸ is halfway between 1 + 2⁻⁷ (odd) and 1 + 2⁻⁶ (even): up.
    assert_eq!(round_bf16(1.0 + 3.0 / 256.0), 1.0 + 1.0 / 64.0);
    assert!(round_bf16(f32::NAN).is_nan());
    assert_eq!(round_bf16(f32::INFINITY), f32::INFINITY);
    for x in [0.1f32, 3.3, -7.77, 1e-3, 12345.0] {
        assert!((round_bf16(x) - x).abs() <= x.abs() / 256.0, "{x}");
    }
}

/// A head in a reduced precision (bfloat16: native `VDPBF16PS` where the core has it; f16:
/// native `VFMADD231PH`) against its emulation on the f32 GEMM, which rounds the same values,
/// and against the f32 head: row counts around the kernels' 6-, 12- and 32-row blocks and the
/// tile, a width that pads to the 64-column panel, and the shipped head.
fn assert_reduced_close(
    fused: &alignist::net::FusedHead,
    encoding: &RotationEncoding,
    precision: alignist::net::Precision,
    tolerance: Tolerance,
    what: &str,
) {
    let native = |image: &[f32], rows: alignist::net::Rows<'_>| {
        fused.branch_scores_in(precision, image, rows)
    };
    assert_kernel_close(fused, encoding, precision, &native, tolerance, what);
}

/// A kernel's `(s_θ, s_φ)` of rows, for an image's term.
type BranchScoresOf<'a> = dyn Fn(&[f32], alignist::net::Rows<'_>) -> (Vec<f32>, Vec<f32>) + 'a;

/// [`assert_reduced_close`] for the kernel `got`.
fn assert_kernel_close(
    fused: &alignist::net::FusedHead,
    encoding: &RotationEncoding,
    precision: alignist::net::Precision,
    got: &BranchScoresOf<'_>,
    tolerance: Tolerance,
    what: &str,
) {
    use alignist::net::ReducedHead;
    use alignist::net::Rows;
    let emulated = ReducedHead::emulated(fused, precision);
    let tile = alignist::net::tiles::tile_rows();
    for rows in [
        1,
        5,
        6,
        7,
        12,
        13,
        33,
        tile - 1,
        tile,
        tile + 1,
        2 * tile + 3,
    ] {
        let rotations = spread_rotations(rows, 0.0);
        let features: Vec<f32> = (0..fused.image_dim())
            .map(|i| ((i * 37 + rows) % 17) as f32 / 17.0)
            .collect();
        let image = fused.image_term(&features);
        let encodings = encoding.encode(&rotations);
        let projected = fused.project_rotations(&encodings);
        let f32_scores = fused.branch_scores(&image, &projected);
        // The rows as f32 projections (a search's start level) and as encodings (the finer
        // levels, where the projection runs in bfloat16 inside the tiles).
        let reduced = |rows: Rows<'_>| (got(&image, rows), emulated.branch_scores(&image, rows));
        let from_projections = reduced(Rows::Projected(&projected));
        let from_encodings = reduced(Rows::Encoded(&encodings));
        for (branch, exact, got, emulated) in [
            (
                "shape",
                &f32_scores.0,
                &from_projections.0.0,
                &from_projections.1.0,
            ),
            (
                "feature",
                &f32_scores.1,
                &from_projections.0.1,
                &from_projections.1.1,
            ),
            (
                "shape from encodings",
                &f32_scores.0,
                &from_encodings.0.0,
                &from_encodings.1.0,
            ),
            (
                "feature from encodings",
                &f32_scores.1,
                &from_encodings.0.1,
                &from_encodings.1.1,
            ),
        ] {
            assert_eq!(got.len(), rows);
            let label = format!("{what} {branch}, {rows} rows");
            assert_branch_close(&label, precision, tolerance, [exact, got, emulated]);
        }
    }
}

/// One branch's scores of a kernel (`got`) against its emulation and the f32 head's (`exact`),
/// row by row and on average, [`assert_kernel_close`]'s checks.
fn assert_branch_close(
    label: &str,
    precision: alignist::net::Precision,
    tolerance: Tolerance,
    [exact, got, emulated]: [&[f32]; 3],
) {
    let rows = exact.len();
    let scale = exact.iter().map(|v| v.abs()).sum::<f32>() / rows as f32;
    let (mut worst, mut mean, mut flipped) = (0.0f32, 0.0f32, 0);
    for i in 0..rows {
        let (g, e, x) = (got[i], emulated[i], exact[i]);
        // The same rounded products, summed in another order (the f16 kernel: partly in
        // f16): a rounding may flip between layers, so they agree closely, not exactly.
        // Where a flip lands on a large weight the row moves further: one row in 127
        // rotations of the shipped head's 8-bit feature branch (0.5 % of its score, the
        // shape branch of the same row within 4e-3), so one row in a hundred may, up to
        // four times the tolerance.
        let gap = (g - e).abs() / x.abs().max(scale);
        if gap > tolerance.emulated {
            flipped += 1;
            assert!(
                gap <= 4.0 * tolerance.emulated && flipped <= rows.div_ceil(100),
                "{label}, row {i}: {precision} {g} against its emulation {e} ({flipped} rows beyond {})",
                tolerance.emulated
            );
        }
        worst = worst.max((g - x).abs() / x.abs().max(scale));
        mean += (g - e).abs() / scale / rows as f32;
    }
    eprintln!(
        "{label}: {precision} worst {worst:.4} from f32, mean gap to the emulation {mean:.5}"
    );
    // Most rows agree far more closely than the worst one.
    assert!(
        mean <= tolerance.emulated_mean,
        "{label}: mean gap to the emulation {mean}"
    );
    // bfloat16 keeps 8 significant bits; f16 11, but sums chunks in f16: within a few %
    // of the f32 scores.
    assert!(
        worst <= tolerance.f32,
        "{label}: {precision} {worst} from f32"
    );
}

/// [`assert_reduced_close`] on a small random head (width 40) and on the shipped one.
fn assert_heads_close(precision: Precision, tolerance: Tolerance) {
    assert_heads_close_on(precision, tolerance, alignist::net::Kernels::from_env());
}

/// [`assert_heads_close`] with the heads' kernels capped at `kernels`.
fn assert_heads_close_on(
    precision: Precision,
    tolerance: Tolerance,
    kernels: alignist::net::Kernels,
) {
    use alignist::net::FusedHead;
    let d = device();
    let encoding = RotationEncoding::Cube;
    let head = HeadConfig::new(32, encoding.dim())
        .with_hidden(40)
        .with_layers(4)
        .init(&d)
        .with_output_biases(-2.5, 1.5);
    let small = FusedHead::with_kernels(&head, kernels);
    assert_reduced_close(&small, &encoding, precision, tolerance, "width 40");
    let bundle = alignist::bundle::model::ModelBundle::load(std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/models/symsol1"
    )))
    .unwrap();
    let fused = FusedHead::with_kernels(&bundle.network.head, kernels);
    eprintln!(
        "{precision} on this core, kernels {kernels}: {}",
        fused.kernel_name(precision)
    );
    let encoding = &bundle.manifest.network.encoding;
    assert_reduced_close(&fused, encoding, precision, tolerance, "shipped");
}

#[test]
fn the_bf16_head_agrees_with_its_emulation_and_stays_near_f32() {
    assert_heads_close(Precision::Bf16, Tolerance::BF16);
    // Under `widest` a core with AMX-BF16 runs the AMX tiles above; here the VDPBF16PS kernel.
    assert_heads_close_on(
        Precision::Bf16,
        Tolerance::BF16,
        alignist::net::Kernels::Avx512,
    );
}

/// The AMX kernel's loop, tile pointers and epilogue on tiles emulated in software (on any
/// core; on a core with AMX the test above runs the tiles themselves): the same bfloat16 values
/// as the emulation on the f32 GEMM, within the bfloat16 head's tolerances, on a width that
/// pads to the 32-column panel and on the shipped head.
#[test]
fn the_amx_kernel_on_emulated_tiles_agrees_with_the_bf16_emulation() {
    assert_emulated_tiles_close(
        Precision::Bf16,
        Tolerance::BF16,
        alignist::net::ReducedHead::amx_emulated,
        "AMX bf16 tiles, emulated",
    );
}

/// A small random head (width 40, padded to the kernels' panels, output biases set) on
/// `encoding`, and the shipped bundle: the two heads the kernel tests compare on.
fn small_head_and_shipped(
    encoding: &RotationEncoding,
) -> (
    alignist::net::DualHead,
    alignist::bundle::model::ModelBundle,
) {
    let head = HeadConfig::new(32, encoding.dim())
        .with_hidden(40)
        .with_layers(4)
        .init(&device())
        .with_output_biases(-2.5, 1.5);
    let bundle = alignist::bundle::model::ModelBundle::load(std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/models/symsol1"
    )))
    .unwrap();
    (head, bundle)
}

/// A head on emulated tiles (`tiles_of` a head on the portable kernels) against the emulation of
/// `precision` on the f32 GEMM, on a small random head (width 40) and on the shipped one.
fn assert_emulated_tiles_close(
    precision: Precision,
    tolerance: Tolerance,
    tiles_of: fn(&alignist::net::FusedHead) -> alignist::net::ReducedHead,
    kernel: &str,
) {
    use alignist::net::{FusedHead, Kernels};
    let encoding = RotationEncoding::Cube;
    let (head, bundle) = small_head_and_shipped(&encoding);
    for (fused, encoding, what) in [
        (
            FusedHead::with_kernels(&head, Kernels::Portable),
            &encoding,
            "width 40",
        ),
        (
            FusedHead::with_kernels(&bundle.network.head, Kernels::Portable),
            &bundle.manifest.network.encoding,
            "shipped",
        ),
    ] {
        let tiles = tiles_of(&fused);
        assert_eq!(tiles.kernel_name(), kernel);
        assert!(!tiles.is_native());
        let got = |image: &[f32], rows: alignist::net::Rows<'_>| tiles.branch_scores(image, rows);
        let what = format!("{what}, {kernel}");
        assert_kernel_close(&fused, encoding, precision, &got, tolerance, &what);
    }
}

/// The same for f16. Its 11 significant bits round the products 8 times more finely than
/// bfloat16, but the native kernel sums up to 128 of them in f16, so it is as near f32 as
/// bfloat16 on its worst rows and further from its emulation (which sums in f32).
#[test]
fn the_f16_head_agrees_with_its_emulation_and_stays_near_f32() {
    assert_heads_close(Precision::F16, Tolerance::F16);
}

/// The same for 8-bit integers: weights per column and activations per row on 256-step grids,
/// exact integer sums. The emulation rounds the same values, so the two differ only where the
/// f32 sums' order flips a byte's rounding.
#[test]
fn the_i8_head_agrees_with_its_emulation_and_stays_near_f32() {
    // Under `widest` a core with AMX-INT8 runs the tiles (`TDPBUSD`); capped at AVX-512, the
    // 512-bit `VPDPBUSD` kernel.
    assert_heads_close(Precision::I8, Tolerance::I8);
    assert_heads_close_on(Precision::I8, Tolerance::I8, alignist::net::Kernels::Avx512);
    // The 256-bit AVX-VNNI kernel, where the core has it (else the emulation again).
    assert_heads_close_on(Precision::I8, Tolerance::I8, alignist::net::Kernels::Avx2);
}

/// The 8-bit head on AVX2's `VPMADDWD` kernel (the bytes widened to 16-bit pairs), which cores
/// with AVX2 and no VNNI run: within the 8-bit tolerances of the emulation on a width that pads
/// to the 64-column panel and on the shipped head, on any core with AVX2; and where the core has
/// AVX-VNNI, the very scores of the 256-bit `VPDPBUSD` kernel (the same exact integer sums, the
/// same blocks and epilogue).
#[test]
fn the_i8_head_on_avx2_pairs_agrees_with_its_emulation_and_the_vnni_kernel() {
    use alignist::net::{FusedHead, Kernels, ReducedHead, Rows};
    let encoding = RotationEncoding::Cube;
    let (head, bundle) = small_head_and_shipped(&encoding);
    for (head, encoding, what) in [
        (&head, &encoding, "width 40"),
        (
            &bundle.network.head,
            &bundle.manifest.network.encoding,
            "shipped",
        ),
    ] {
        let fused = FusedHead::with_kernels(head, Kernels::Avx2);
        let Some(pairs) = ReducedHead::i8_avx2_pairs(&fused) else {
            eprintln!("this core has no AVX2: the pairs kernel does not run here");
            return;
        };
        assert_eq!(pairs.kernel_name(), alignist::net::i8::KERNEL_NAME_PAIRS);
        assert!(pairs.is_native());
        let got = |image: &[f32], rows: Rows<'_>| pairs.branch_scores(image, rows);
        let what = format!("{what}, AVX2 pairs");
        assert_kernel_close(&fused, encoding, Precision::I8, &got, Tolerance::I8, &what);
        // Capped at 256 bits, the fused head's own 8-bit kernel: AVX-VNNI where the core has it.
        if fused.kernel_name(Precision::I8) != "AVX-VNNI kernel (256-bit)" {
            eprintln!("{what}: no AVX-VNNI on this core to compare with");
            continue;
        }
        let rotations = spread_rotations(2 * alignist::net::tiles::tile_rows() + 7, 0.0);
        let features: Vec<f32> = (0..fused.image_dim())
            .map(|i| (i % 13) as f32 / 13.0)
            .collect();
        let image = fused.image_term(&features);
        let encodings = encoding.encode(&rotations);
        let projected = fused.project_rotations(&encodings);
        for rows in [Rows::Projected(&projected), Rows::Encoded(&encodings)] {
            assert_eq!(
                pairs.branch_scores(&image, rows),
                fused.branch_scores_in(Precision::I8, &image, rows),
                "{what}: the same sums as VPDPBUSD"
            );
        }
    }
}

/// The 8-bit head's tile kernel (`TDPBUSD`: its loop, tile pointers into the packed panels and
/// epilogue) on tiles emulated in software, on any core (a core with AMX-INT8 runs the tiles
/// themselves in the test above): the emulation's scores within the 8-bit tolerances, on a
/// width that pads to the 64-column panel and on the shipped head.
#[test]
fn the_amx_int8_kernel_on_emulated_tiles_agrees_with_the_i8_emulation() {
    assert_emulated_tiles_close(
        Precision::I8,
        Tolerance::I8,
        alignist::net::ReducedHead::amx_int8_emulated,
        "AMX int8 tiles, emulated",
    );
}

/// How far a reduced-precision head may be from its emulation and from f32, relative to a
/// score's size (at least the mean |score|).
#[derive(Clone, Copy)]
struct Tolerance {
    /// Every row, to the emulation.
    emulated: f32,
    /// The mean over the rows, to the emulation.
    emulated_mean: f32,
    /// Every row, to f32.
    f32: f32,
}

impl Tolerance {
    /// The same rounded products summed in f32 in another order: a few bfloat16 steps.
    const BF16: Tolerance = Tolerance {
        emulated: 4e-3,
        emulated_mean: 5e-4,
        f32: 0.03,
    };
    /// The native kernel sums in f16 within chunks, the emulation in f32 (measured on the
    /// shipped head: worst 0.8 % from f32, mean gap to the emulation 0.3 %).
    const F16: Tolerance = Tolerance {
        emulated: 0.02,
        emulated_mean: 5e-3,
        f32: 0.02,
    };
    /// Bytes round 8 times more coarsely than f16, but the sums are exact and the emulation
    /// rounds the same values (measured on the shipped heads: worst 3.3 % from f32 on r9's,
    /// 5.6 % on r11's, in one of 12 rows; mean gap to the emulation below 1e-5 on both).
    const I8: Tolerance = Tolerance {
        emulated: 4e-3,
        emulated_mean: 5e-4,
        f32: 0.08,
    };
}

/// The hand-written inference encoder (BatchNorms folded into the convolutions, ReLU and the
/// residual add on the GEMM's output) computes burn's eval-mode features: on the shipped
/// `tiny_deep` encoder (projection shortcuts, strided stages, trained running statistics) and on
/// a fresh `tiny` one after two training-mode passes, at batches of 1 and 3,
/// under the widest kernels and capped at AVX2 (matrixmultiply's GEMM), with the direct 3 × 3
/// kernels where the core has them and with im2col and the GEMM alone.
#[test]
fn the_folded_inference_encoder_computes_burns_eval_features() {
    use alignist::net::{EncoderConfig, InferenceEncoder, Kernels, ResNetLayout, network};
    let conv = alignist::backend::device_for(alignist::backend::Workload::Conv);
    let bundle = alignist::bundle::model::ModelBundle::load(std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/models/symsol1"
    )))
    .unwrap();
    let side = bundle.manifest.network.image_size as usize;
    let crop = |seed: usize, side: usize| -> Vec<u8> {
        (0..side * side * 3)
            .map(|i| ((i * 131 + seed * 977) % 251) as u8)
            .collect()
    };
    // A fresh tiny encoder, its running statistics updated by two training-mode passes.
    let train = conv.clone().autodiff();
    train.seed(7);
    let fresh = EncoderConfig::new(ResNetLayout::Tiny).init(&train);
    for seed in 0..2 {
        let crops: Vec<Vec<u8>> = (0..4).map(|i| crop(10 * seed + i, 32)).collect();
        let refs: Vec<&[u8]> = crops.iter().map(Vec::as_slice).collect();
        let _ = fresh.forward(network::images_tensor(&refs, 32, &train));
    }
    let fresh = burn::module::Module::valid(&fresh);
    // Pooled over 2 × 2 cells of its 4 × 4 map, and over 3 × 3 overlapping cells.
    let (grid2, grid3) = (
        fresh.clone().with_pool_grid(2),
        fresh.clone().with_pool_grid(3),
    );
    for (encoder, side, what) in [
        (&bundle.network.encoder, side, "shipped"),
        (&fresh, 32, "fresh tiny"),
        (&grid2, 32, "fresh tiny, 2 × 2 grid"),
        (&grid3, 32, "fresh tiny, 3 × 3 grid"),
    ] {
        for (kernels, direct) in [
            (Kernels::Widest, true),
            (Kernels::Avx2, true),
            (Kernels::Widest, false),
        ] {
            let folded = InferenceEncoder::of(encoder, kernels).expect("a CPU layout");
            let folded = if direct { folded } else { folded.im2col_only() };
            // Where the core has AVX2 and FMA, every 3 × 3 unit whose output is 8 wide or more
            // runs direct, and the encoder says so.
            #[cfg(target_arch = "x86_64")]
            let has = std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma");
            #[cfg(not(target_arch = "x86_64"))]
            let has = false;
            let paths = folded.kernel_paths(side);
            assert_eq!(folded.has_direct(), direct && has, "{what}: {paths}");
            assert_eq!(
                paths.contains("direct 3×3"),
                direct && has,
                "{what}: {paths}"
            );
            let kernels = format!("{kernels}{}", if direct { "" } else { ", im2col only" });
            for batch in [1usize, 3] {
                let crops: Vec<Vec<u8>> = (0..batch).map(|i| crop(i, side)).collect();
                let refs: Vec<&[u8]> = crops.iter().map(Vec::as_slice).collect();
                let want: Vec<f32> = network::feature_rows(
                    encoder.forward(network::images_tensor(&refs, side, &conv)),
                )
                .concat();
                let got = folded.features(&refs, side).concat();
                assert_eq!(got.len(), want.len(), "{what}");
                let scale = want.iter().map(|v| v.abs()).fold(0f32, f32::max);
                let worst = got
                    .iter()
                    .zip(&want)
                    .map(|(g, w)| (g - w).abs())
                    .fold(0f32, f32::max);
                eprintln!("{what}, {kernels}, batch {batch}: worst {worst:.2e} of max {scale:.3}");
                assert!(scale > 0.0, "{what}: features all zero");
                assert!(
                    worst <= 1e-4 * scale.max(1.0),
                    "{what} {kernels} batch {batch}: {worst}"
                );
            }
        }
    }
}

/// The shape branch alone (`Branches::Shape`, what a search's coarse levels may rank by) on every
/// path a head scores on: the f32 head on the portable and the widest kernels, each reduced
/// precision, the AMX kernels on emulated tiles and AVX2's 8-bit pairs. Its `s_θ` is, to the
/// bit, the one both branches give (a row's shape branch never reads the feature branch), and the
/// feature branch it leaves out scores 0; from projections and from encodings, over rows around
/// the tile, on a width that pads to the panel and on the shipped head.
#[test]
fn the_shape_branch_alone_scores_as_it_does_beside_the_feature_branch() {
    use alignist::net::{Branches, FusedHead, Kernels, ReducedHead, Rows};
    let encoding = RotationEncoding::Cube;
    let (head, bundle) = small_head_and_shipped(&encoding);
    let tile = alignist::net::tiles::tile_rows();
    for (head, encoding, what) in [
        (&head, &encoding, "width 40"),
        (
            &bundle.network.head,
            &bundle.manifest.network.encoding,
            "shipped",
        ),
    ] {
        for kernels in [Kernels::Portable, Kernels::from_env()] {
            let fused = FusedHead::with_kernels(head, kernels);
            let mut paths: Vec<(String, Box<BranchScoresBy<'_>>)> = Vec::new();
            for precision in [
                Precision::F32,
                Precision::Bf16,
                Precision::F16,
                Precision::I8,
            ] {
                let fused = &fused;
                paths.push((
                    format!("{precision}, {}", fused.kernel_name(precision)),
                    Box::new(move |image, rows, branches| {
                        fused.branch_scores_of(precision, image, rows, branches)
                    }),
                ));
            }
            let mut tiles = vec![
                ReducedHead::amx_emulated(&fused),
                ReducedHead::amx_int8_emulated(&fused),
            ];
            tiles.extend(ReducedHead::i8_avx2_pairs(&fused));
            for t in tiles {
                paths.push((
                    t.kernel_name().to_string(),
                    Box::new(move |image, rows, branches| {
                        t.branch_scores_of(image, rows, branches)
                    }),
                ));
            }
            for rows in [1, 7, 13, tile + 1] {
                let rotations = spread_rotations(rows, 0.5);
                let features: Vec<f32> = (0..fused.image_dim())
                    .map(|i| ((i * 29 + rows) % 19) as f32 / 19.0)
                    .collect();
                let image = fused.image_term(&features);
                let encodings = encoding.encode(&rotations);
                let projected = fused.project_rotations(&encodings);
                for (name, scores) in &paths {
                    for given in [Rows::Projected(&projected), Rows::Encoded(&encodings)] {
                        let both = scores(&image, given, Branches::Both);
                        let (shape, feature) = scores(&image, given, Branches::Shape);
                        assert_eq!(shape, both.0, "{what}, {name}, {rows} rows");
                        assert!(
                            feature.iter().all(|&f| f == 0.0),
                            "{what}, {name}: the feature branch left out scores 0"
                        );
                        assert!(both.1.iter().any(|&f| f != 0.0), "{what}, {name}");
                    }
                }
            }
        }
    }
}

/// A path's `(s_θ, s_φ)` of rows by branches, for an image's term.
type BranchScoresBy<'a> =
    dyn Fn(&[f32], alignist::net::Rows<'_>, alignist::net::Branches) -> (Vec<f32>, Vec<f32>) + 'a;
