//! The trainer: real steps on a tiny set, deterministic for a seed, and a run interrupted after a
//! checkpoint resumes to exactly the weights of an uninterrupted run.

mod common;

use std::ops::ControlFlow;

use alignist::bundle::experts::{bake_experts, key_siren_config};
use alignist::cad::Shape;
use alignist::encoding::RotationEncoding;
use alignist::experts::SirenConfig;
use alignist::experts::energy::EnergyParams;
use alignist::experts::modes::{ModeTable, ModeTableConfig};
use alignist::experts::select::visible_points_at;
use alignist::net::ResNetLayout;
use alignist::net::images_tensor;
use alignist::so3::{GridLevel, haar_rotations};
use alignist::train::data::FreshRenders;
use alignist::train::{
    MeasureLoss, Method, Network, NetworkConfig, OwnTwins, SamplingStrategy, TrainConfig,
    TrainingImage, TrainingSet, train, train_replanned,
};
use common::tensors;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const SIZE: u32 = 32;

/// A tiny set: cube crops with visible points, and (untrained, quickly baked) experts — enough
/// for the mechanics of training; the experts' quality is tested elsewhere.
fn tiny_set() -> TrainingSet {
    let device = alignist::backend::device();
    let mesh = Shape::Cube.mesh();
    let baked = bake_experts(
        &SirenConfig::new(3, 32, 2, 1).init(&device),
        &key_siren_config().init(&device),
        12,
        1.05,
        EnergyParams::default(),
        &device,
    );
    let camera = alignist::cad::Camera::square(SIZE);
    let images = haar_rotations(&mut ChaCha8Rng::seed_from_u64(5), 8)
        .into_iter()
        .enumerate()
        .map(|(i, r)| {
            let render = alignist::cad::render(
                &mesh,
                &camera,
                &alignist::data::symsol_pose(r),
                &alignist::cad::RenderOptions::default(),
            );
            TrainingImage {
                object: 0,
                rgb: render.rgb,
                rotation: r,
                visible: visible_points_at(&mesh, &r, i as u64),
            }
        })
        .collect();
    let modes = ModeTable::build(
        &baked,
        &mesh,
        &ModeTableConfig {
            views: 2,
            coarse_level: 1,
            level: 2,
            keep_fraction: 0.02,
            seed: 0,
        },
    )
    .unwrap();
    TrainingSet {
        objects: vec![baked],
        modes: vec![modes],
        twins: Vec::new(),
        symmetries: Vec::new(),
        images,
        fresh: None,
    }
}

/// [`tiny_set`], but every step renders new crops (its fixed images are only for fingerprints).
fn tiny_fresh_set() -> TrainingSet {
    TrainingSet {
        fresh: Some(FreshRenders {
            meshes: vec![Shape::Cube.mesh()],
            supersample: 2,
            pool: None,
            realism: None,
        }),
        ..tiny_set()
    }
}

fn config(method: Method) -> TrainConfig {
    TrainConfig {
        network: NetworkConfig::new(ResNetLayout::Tiny, RotationEncoding::Cube)
            .with_image_size(SIZE)
            .with_hidden(32),
        method,
        steps: 6,
        batch: 2,
        k: 64,
        lr: 1e-3,
        warmup: 2,
        seed: 11,
        checkpoint_every: 3,
        init: None,
        teacher: None,
        plain_start: None,
        pretrained: None,
        pretrained_file: None,
        encoder_lr_scale: None,
        contrast: None,
        target_temperature: None,
    }
}

fn alignist_method() -> Method {
    Method::Alignist {
        loss: MeasureLoss::Gkl,
        sampling: SamplingStrategy::ModeFocused {
            focused: 40,
            temperature: 0.0,
            focused_end: None,
            twin_share: 0.0,
            own_twins: None,
        },
        experts: Default::default(),
    }
}

/// Scores of a fixed input, to compare networks.
fn fingerprint(network: &Network, set: &TrainingSet) -> Vec<f32> {
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv);
    let crops: Vec<&[u8]> = set
        .images
        .iter()
        .take(2)
        .map(|i| i.rgb.as_slice())
        .collect();
    let images = images_tensor(&crops, SIZE as usize, &device);
    let grid = GridLevel::new(0).unwrap().matrices_f32();
    let scores = network.scores(images, &[grid.clone(), grid], &RotationEncoding::Cube);
    scores.combined().into_data().try_to_vec::<f32>().unwrap()
}

#[test]
fn training_is_deterministic_and_resumes_exactly() {
    deterministic_and_resumes_exactly(tiny_set(), alignist_method());
}

#[test]
fn training_on_fresh_renders_is_deterministic_and_resumes_exactly() {
    deterministic_and_resumes_exactly(tiny_fresh_set(), alignist_method());
}

/// [`alignist_method`] with half its focused rotations around twins, and the network's own
/// searched on 12 crops every 2 steps (the cube's set records no symmetry, so no near-symmetry
/// twins either: every twin is the network's own).
fn own_twins_method() -> Method {
    let Method::Alignist {
        loss,
        sampling,
        experts,
    } = alignist_method()
    else {
        unreachable!("alignist_method is Alignist")
    };
    Method::Alignist {
        loss,
        sampling: sampling.with_twin_share(0.5).with_own_twins(Some(OwnTwins {
            crops: 12,
            every: 2,
        })),
        experts,
    }
}

#[test]
fn the_networks_own_twins_are_found_checkpointed_and_resume_exactly() {
    // Searched at steps 0, 2 and 4; the checkpoint of step 3 holds step 2's, and the run killed
    // after step 4 resumes from it to the same weights.
    deterministic_and_resumes_exactly(tiny_fresh_set(), own_twins_method());
    let set = tiny_fresh_set();
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(own_twins_method());
    let (with_own, report) = train(&cfg, &set, Some(dir.path()), false, |_, _, _| {
        ControlFlow::Continue(())
    })
    .unwrap();
    let searched: Vec<usize> = report.own_twins.iter().map(|f| f.step).collect();
    assert_eq!(
        searched,
        [0, 2, 4],
        "searched before the first step and every 2"
    );
    let state: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("step-00000003/state.json")).unwrap(),
    )
    .unwrap();
    let twins = state["own_twins"][0]
        .as_array()
        .expect("the cube's own twins");
    assert!(
        !twins.is_empty(),
        "an untrained network misses by a half-turn"
    );
    assert_eq!(twins.len(), report.own_twins[1].misses[0], "step 2's twins");
    for m in twins {
        let m: Vec<f64> = serde_json::from_value(m.clone()).unwrap();
        let r = alignist::so3::from_row_major(m.try_into().unwrap()).unwrap();
        assert!(
            r.angle().to_degrees() >= 150.0,
            "{}°",
            r.angle().to_degrees()
        );
    }
    // The same run without its own twins (a twin share, but no twins to draw around) trains
    // other weights.
    let without = config(Method::Alignist {
        loss: MeasureLoss::Gkl,
        sampling: match own_twins_method() {
            Method::Alignist { sampling, .. } => sampling.with_own_twins(None),
            Method::Ipdf => unreachable!(),
        },
        experts: Default::default(),
    });
    let (plain, _) = train(&without, &set, None, false, |_, _, _| {
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_ne!(fingerprint(&with_own, &set), fingerprint(&plain, &set));
}

fn deterministic_and_resumes_exactly(set: TrainingSet, method: Method) {
    let cfg = config(method);
    let mut losses = Vec::new();
    let (a, report) = train(&cfg, &set, None, false, |_, _, l| {
        losses.push(l);
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(report.steps_run, 6);
    assert!(
        losses.iter().all(|l| l.is_finite() && *l >= 0.0),
        "{losses:?}"
    );
    let (b, _) = train(&cfg, &set, None, false, |_, _, _| ControlFlow::Continue(())).unwrap();
    assert_eq!(
        fingerprint(&a, &set),
        fingerprint(&b, &set),
        "same seed, same weights"
    );

    // Interrupted after step 4 (its last checkpoint is step 3), then resumed.
    let dir = tempfile::tempdir().unwrap();
    let (_, first) = train(&cfg, &set, Some(dir.path()), true, |step, _, _| {
        if step == 4 {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    })
    .unwrap();
    assert_eq!(first.steps_run, 4);
    assert_eq!(
        std::fs::read_to_string(dir.path().join("latest")).unwrap(),
        "step-00000003"
    );
    let (resumed, second) = train(&cfg, &set, Some(dir.path()), true, |_, _, _| {
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(second.resumed_from, 3);
    assert_eq!(second.steps_run, 3);
    // Weights and BatchNorm running statistics alike: every saved tensor is bit-identical.
    let files = tempfile::tempdir().unwrap();
    let sa = alignist::bundle::save_weights(&a, &files.path().join("a.safetensors")).unwrap();
    let sr = alignist::bundle::save_weights(&resumed, &files.path().join("r.safetensors")).unwrap();
    assert_eq!(sa.bytes, sr.bytes);
    let (ta, tr) = (
        tensors(&files.path().join("a.safetensors")),
        tensors(&files.path().join("r.safetensors")),
    );
    assert_eq!(ta.len(), tr.len());
    for (name, data) in &ta {
        assert!(tr.get(name) == Some(data), "{name} differs after resume");
    }
    assert_eq!(fingerprint(&a, &set), fingerprint(&resumed, &set));

    // The network file of a bundle reads back to the same scores, bit for bit.
    let entry =
        alignist::bundle::save_weights(&a, &files.path().join("network.safetensors")).unwrap();
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv);
    let loaded = alignist::bundle::load_weights(
        cfg.network.init(&device),
        &files.path().join("network.safetensors"),
        &entry,
    )
    .unwrap();
    let (fa, fl) = (fingerprint(&a, &set), fingerprint(&loaded, &set));
    assert!(fa.iter().zip(&fl).all(|(x, y)| x.to_bits() == y.to_bits()));

    // Another seed gives other weights.
    let other = TrainConfig { seed: 12, ..cfg };
    let (c, _) = train(&other, &set, None, false, |_, _, _| {
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_ne!(fingerprint(&a, &set), fingerprint(&c, &set));
}

#[test]
fn ipdf_baseline_trains_on_the_same_network() {
    let set = tiny_set();
    let cfg = config(Method::Ipdf);
    let mut losses = Vec::new();
    let (_, report) = train(&cfg, &set, None, false, |_, _, l| {
        losses.push(l);
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(report.steps_run, 6);
    // −log softmax over 64 rotations starts near log 64.
    assert!((losses[0] - (64f64).ln()).abs() < 1.0, "{losses:?}");
}

/// Real (small) experts of the cube (200 SDF and 200 feature steps, 32³ bakes) and fresh renders
/// of it: a training set of fresh renders.
fn cube_with_small_experts() -> (TrainingSet, FreshRenders) {
    use alignist::experts::feature::FeatureTrainConfig;
    use alignist::experts::sdf::SdfTrainConfig;
    use alignist::train::experts::{ExpertsJob, train_expert_set};
    let shape = Shape::Cube;
    let (mesh, normalisation) = shape.mesh().normalised();
    let experts = train_expert_set(
        ExpertsJob {
            name: "cube".into(),
            mesh: mesh.clone(),
            normalisation,
            symmetries: shape.symmetries(),
            sdf: SdfTrainConfig {
                steps: 200,
                ..Default::default()
            },
            features: FeatureTrainConfig {
                steps: 200,
                ..Default::default()
            },
            bake_resolution: 32,
            energy: Default::default(),
            width: Default::default(),
            modes: Default::default(),
            command: "test".into(),
        },
        &mut |_, _, _, _| {},
    )
    .unwrap();
    let device = alignist::backend::device();
    let baked = alignist::bundle::experts::bake_experts(
        &experts.sdf,
        &experts.keys,
        32,
        1.05,
        experts.manifest.energy,
        &device,
    );
    let fresh = FreshRenders {
        meshes: vec![mesh.clone()],
        supersample: 2,
        pool: None,
        realism: None,
    };
    let set = TrainingSet {
        objects: vec![baked],
        modes: vec![experts.modes.clone().unwrap()],
        twins: Vec::new(),
        symmetries: Vec::new(),
        images: Vec::new(),
        fresh: Some(fresh.clone()),
    };
    (set, fresh)
}

#[test]
fn a_few_hundred_real_steps_lower_the_loss_and_beat_uniform_on_held_out_renders() {
    use alignist::so3::metrics::chance_accuracy;
    use alignist::train::eval::evaluate;
    let shape = Shape::Cube;
    let (set, fresh) = cube_with_small_experts();
    let cfg = TrainConfig {
        steps: 300,
        batch: 16,
        k: 256,
        lr: 1e-3,
        warmup: 10,
        ..config(Method::Alignist {
            loss: MeasureLoss::Gkl,
            sampling: SamplingStrategy::mode_focused(256),
            experts: Default::default(),
        })
    };
    let mut losses = Vec::new();
    let (network, train_report) = train(&cfg, &set, None, false, |_, _, l| {
        losses.push(l);
        ControlFlow::Continue(())
    })
    .unwrap();
    let first: f64 = losses[..30].iter().sum::<f64>() / 30.0;
    let last: f64 = losses[losses.len() - 30..].iter().sum::<f64>() / 30.0;
    assert!(last < 0.98 * first, "loss {first} → {last}");
    let held_out = fresh.eval_images(&["cube".into()], &[shape.symmetries()], SIZE, 100, 77);
    let report = evaluate(&network, &cfg.network, &held_out, 2, |_| {}).unwrap();
    eprintln!(
        "loss {first:.3} → {last:.3}; held-out {:?}; profile {:?}",
        report.overall, train_report.profile
    );
    // Better than uniform (LL 0) and than an argmax that ignores the image, on renders it never
    // saw.
    assert!(report.overall.log_likelihood > 0.0, "{:?}", report.overall);
    assert_eq!(report.overall.images, 100);
    let chance = chance_accuracy(&shape.symmetries(), 30.0, 20_000, 1);
    assert!((0.15..0.21).contains(&chance), "cube chance AR@30 {chance}");
    assert!(
        report.overall.accuracy_at[0].1 > chance + 0.05,
        "AR@30 {:?} vs chance {chance}",
        report.overall.accuracy_at
    );
    // The profile's stages add up to the step (within 10 %).
    let p = train_report.profile;
    assert_eq!(p.steps, 300);
    assert!(
        (p.stages() - p.total).abs() < 0.1 * p.total,
        "stages {} vs step {}",
        p.stages(),
        p.total
    );
}

#[test]
fn the_training_bench_prints_both_steps_and_their_ratio() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_alignist-train"))
        .args([
            "bench",
            "--training",
            "--batch",
            "2",
            "--k",
            "16",
            "--steps",
            "2",
        ])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for line in ["ipdf step: ", "alignist step: ", "head forward: "] {
        assert!(text.contains(line), "{line} missing in {text}");
    }
    let ratio: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("alignist/ipdf step time ratio: "))
        .expect("the alignist/ipdf ratio is printed")
        .parse()
        .unwrap();
    assert!(ratio > 0.0 && ratio.is_finite());
    // Last: the ratio to PyTorch where python3 has torch, else why it was not run.
    let last = text.lines().last().unwrap();
    assert!(
        last.starts_with("ipdf step / pytorch ipdf step: ")
            || last.starts_with("pytorch reference not run ("),
        "last line: {last}"
    );
}

/// The network of a first run of `cfg` (trained by `go`), its weights saved in `dir` and
/// recorded as a warm start from them.
fn first_run_saved<E: std::fmt::Debug>(
    go: &impl Fn(&TrainConfig) -> Result<(Network, E), alignist::train::TrainError>,
    cfg: &TrainConfig,
    dir: &std::path::Path,
) -> (Network, alignist::train::config::InitWeights) {
    let (a, _) = go(cfg).unwrap();
    let path = dir.join("network.safetensors");
    let file = alignist::bundle::save_weights(&a, &path).unwrap();
    let init = alignist::train::config::InitWeights {
        path: path.display().to_string(),
        file,
        trained_by: "the test's first run".into(),
        image_size: None,
        layout: None,
        pool_grid: None,
    };
    (a, init)
}

#[test]
fn a_warm_restart_starts_from_the_given_weights_and_checks_them() {
    let set = tiny_set();
    let cfg = config(alignist_method());
    let go = |c: &TrainConfig| train(c, &set, None, false, |_, _, _| ControlFlow::Continue(()));
    let files = tempfile::tempdir().unwrap();
    let (a, init) = first_run_saved(&go, &cfg, files.path());
    // Learning rate 0: the parameters stay where they started (BatchNorm's running statistics
    // still move with the batches, so they are left out of the comparison).
    let warm = TrainConfig {
        lr: 0.0,
        seed: 12,
        init: Some(init),
        ..cfg.clone()
    };
    let parameters = |n: &Network, name: &str| {
        let p = files.path().join(name);
        alignist::bundle::save_weights(n, &p).unwrap();
        let mut t = tensors(&p);
        t.retain(|k, _| !k.contains("running"));
        t
    };
    let (w, _) = go(&warm).unwrap();
    let (ta, tw) = (
        parameters(&a, "a.safetensors"),
        parameters(&w, "w.safetensors"),
    );
    assert!(ta.len() > 10);
    assert_eq!(
        ta, tw,
        "a warm restart at lr 0 must keep the weights it started from"
    );
    // The same run from a seeded initialisation keeps other weights.
    let (s, _) = go(&TrainConfig {
        init: None,
        teacher: None,
        ..warm.clone()
    })
    .unwrap();
    assert_ne!(ta, parameters(&s, "s.safetensors"));
    // A weights file that is not the one recorded is refused, and the error names it.
    let mut other = warm.clone();
    other.init.as_mut().unwrap().file.sha256 = "0".repeat(64);
    let err = go(&other).unwrap_err().to_string();
    assert!(err.contains("network.safetensors"), "{err}");
}

/// A globally pooled network warm-starts one pooled over a grid of cells: at learning rate 0 the
/// grid's network scores as the same warm restart pooled globally (its head's image projection
/// spread over the cells); trained, it departs from it; a grid does not start another grid.
#[test]
fn a_globally_pooled_network_warm_starts_a_grid_pooled_one_with_the_same_scores() {
    use alignist::train::config::InitWeights;
    let set = tiny_set();
    let cfg = config(alignist_method());
    let go = |c: &TrainConfig| train(c, &set, None, false, |_, _, _| ControlFlow::Continue(()));
    let files = tempfile::tempdir().unwrap();
    let (_, init) = first_run_saved(&go, &cfg, files.path());
    let init = InitWeights {
        pool_grid: Some(1),
        ..init
    };
    let grid = TrainConfig {
        lr: 0.0,
        network: cfg.network.clone().pooled_over(2),
        init: Some(init.clone()),
        ..cfg.clone()
    };
    let (g, _) = go(&grid).unwrap();
    assert_eq!(g.encoder.pool_grid(), 2);
    // Against the same warm restart pooled globally (BatchNorm's running statistics move at lr 0
    // too, the same in both).
    let (w, _) = go(&TrainConfig {
        network: cfg.network.clone(),
        ..grid.clone()
    })
    .unwrap();
    let (fa, fg) = (fingerprint(&w, &set), fingerprint(&g, &set));
    let scale = fa.iter().fold(1f32, |m, v| m.max(v.abs()));
    let worst = fa
        .iter()
        .zip(&fg)
        .fold(0f32, |m, (x, y)| m.max((x - y).abs()));
    assert!(
        worst <= 1e-4 * scale,
        "scores moved by {worst} (of {scale})"
    );
    // Trained on, the cells are weighed apart: the scores leave the global network's.
    let (h, _) = go(&TrainConfig {
        lr: 1e-2,
        ..grid.clone()
    })
    .unwrap();
    let fh = fingerprint(&h, &set);
    assert!(
        fa.iter()
            .zip(&fh)
            .any(|(x, y)| (x - y).abs() > 1e-3 * scale)
    );
    // A grid does not warm-start another grid.
    let entry = alignist::bundle::save_weights(&g, &files.path().join("g.safetensors")).unwrap();
    let err = go(&TrainConfig {
        network: cfg.network.clone().pooled_over(3),
        init: Some(InitWeights {
            path: files.path().join("g.safetensors").display().to_string(),
            file: entry,
            pool_grid: Some(2),
            ..init
        }),
        ..cfg.clone()
    })
    .unwrap_err()
    .to_string();
    assert!(err.contains("2×2") && err.contains("3×3"), "{err}");
}

#[test]
fn single_expert_runs_silence_the_other_branch() {
    use alignist::train::ExpertBranches;
    let set = tiny_set();
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv);
    let crops: Vec<&[u8]> = set
        .images
        .iter()
        .take(2)
        .map(|i| i.rgb.as_slice())
        .collect();
    let grid = GridLevel::new(0).unwrap().matrices_f32();
    for (experts, silent_is_shape) in [
        (ExpertBranches::ShapeOnly, false),
        (ExpertBranches::FeatureOnly, true),
    ] {
        let cfg = config(Method::Alignist {
            loss: MeasureLoss::Gkl,
            sampling: SamplingStrategy::ModeFocused {
                focused: 40,
                temperature: 0.0,
                focused_end: None,
                twin_share: 0.0,
                own_twins: None,
            },
            experts,
        });
        let (network, _) =
            train(&cfg, &set, None, false, |_, _, _| ControlFlow::Continue(())).unwrap();
        let images = images_tensor(&crops, SIZE as usize, &device);
        let scores = network.scores(
            images,
            &[grid.clone(), grid.clone()],
            &RotationEncoding::Cube,
        );
        let (silent, live) = if silent_is_shape {
            (scores.shape, scores.feature)
        } else {
            (scores.feature, scores.shape)
        };
        let silent = silent.into_data().try_to_vec::<f32>().unwrap();
        let live = live.into_data().try_to_vec::<f32>().unwrap();
        assert!(
            silent.iter().all(|&v| v == silent[0]),
            "{experts:?}: the silenced branch must be constant"
        );
        assert!(
            live.iter().any(|&v| (v - live[0]).abs() > 1e-6),
            "{experts:?}: the trained branch must vary"
        );
    }
}

#[test]
fn a_pool_of_fresh_renders_repeats_the_same_images_in_every_run() {
    use std::collections::BTreeSet;
    let pooled = FreshRenders {
        meshes: vec![Shape::Cube.mesh(), Shape::Tetrahedron.mesh()],
        supersample: 1,
        pool: Some(3),
        realism: None,
    };
    let seeds = |object: usize, run: u64, fresh: &FreshRenders| -> BTreeSet<u64> {
        let mut rng = ChaCha8Rng::seed_from_u64(run);
        (0..200)
            .map(|_| fresh.image_seed(object, &mut rng))
            .collect()
    };
    let a = seeds(0, 1, &pooled);
    assert_eq!(a.len(), 3);
    assert_eq!(
        a,
        seeds(0, 2, &pooled),
        "the pool does not depend on the run"
    );
    assert!(
        a.is_disjoint(&seeds(1, 1, &pooled)),
        "each object has its own pool"
    );
    let unpooled = FreshRenders {
        pool: None,
        realism: None,
        ..pooled
    };
    assert_eq!(seeds(0, 1, &unpooled).len(), 200);
}

/// A schedule re-planned as it runs (what `new` does when the machine's pace changes) ends at its
/// new length, and a run killed after the re-plan resumes, from the config with the new length,
/// to exactly the weights of the uninterrupted one.
#[test]
fn a_replanned_schedule_ends_at_its_new_length_and_resumes_exactly() {
    let set = tiny_set();
    let cfg = config(Method::Alignist {
        loss: MeasureLoss::Gkl,
        // Annealed: the focused share, like the learning rate, follows the schedule's length.
        sampling: SamplingStrategy::annealed_share(64, 0.75, 0.05),
        experts: Default::default(),
    });
    // 6 steps planned, re-planned at the checkpoint of step 3 to 8.
    let replan = |step: usize| ControlFlow::Continue((step == 3).then_some(8));
    let mut seen = Vec::new();
    let (a, report) = train_replanned(&cfg, &set, None, false, |step, steps, _| {
        seen.push((step, steps));
        replan(step)
    })
    .unwrap();
    assert_eq!(report.steps_run, 8);
    assert_eq!(
        seen,
        [
            (1, 6),
            (2, 6),
            (3, 6),
            (4, 8),
            (5, 8),
            (6, 8),
            (7, 8),
            (8, 8)
        ]
    );
    // Not the run planned for 6 or for 8 from the start.
    let planned_8 = TrainConfig {
        steps: 8,
        ..cfg.clone()
    };
    let (b, _) = train(&planned_8, &set, None, false, |_, _, _| {
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_ne!(fingerprint(&a, &set), fingerprint(&b, &set));

    // Killed after step 4 (last checkpoint: step 3, where it re-planned), resumed with the
    // re-planned length: step 4's batch, drawn ahead for 6 steps, must be drawn again for 8.
    let dir = tempfile::tempdir().unwrap();
    let (_, first) = train_replanned(&cfg, &set, Some(dir.path()), true, |step, _, _| {
        if step == 4 {
            ControlFlow::Break(())
        } else {
            replan(step)
        }
    })
    .unwrap();
    assert_eq!(first.steps_run, 4);
    let (resumed, second) = train(&planned_8, &set, Some(dir.path()), true, |_, _, _| {
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!((second.resumed_from, second.steps_run), (3, 5));
    assert_eq!(fingerprint(&a, &set), fingerprint(&resumed, &set));
}

#[test]
fn a_distilled_head_keeps_the_teachers_encoder_and_learns_its_scores() {
    use alignist::train::config::TeacherWeights;
    let set = tiny_set();
    let go = |c: &TrainConfig| train(c, &set, None, false, |_, _, _| ControlFlow::Continue(()));
    // A teacher trained past its start, so that its scores are its own, not the experts' mean.
    let teacher_cfg = TrainConfig {
        steps: 30,
        ..config(alignist_method())
    };
    let (teacher, _) = go(&teacher_cfg).unwrap();
    let files = tempfile::tempdir().unwrap();
    let path = files.path().join("network.safetensors");
    let entry = alignist::bundle::save_weights(&teacher, &path).unwrap();
    let student = |lr: f64| TrainConfig {
        network: teacher_cfg.network.clone().with_hidden(16),
        steps: 60,
        lr,
        teacher: Some(TeacherWeights {
            path: path.display().to_string(),
            file: entry.clone(),
            network: teacher_cfg.network.clone(),
            trained_by: "the test's teacher".into(),
        }),
        ..config(alignist_method())
    };
    let (before, _) = go(&student(0.0)).unwrap();
    let (after, _) = go(&student(3e-3)).unwrap();
    // The encoder is the teacher's, frozen: every encoder tensor (running statistics too).
    let encoder = |n: &Network, name: &str| {
        let p = files.path().join(name);
        alignist::bundle::save_weights(n, &p).unwrap();
        let mut t = tensors(&p);
        t.retain(|k, _| k.starts_with("encoder"));
        t
    };
    let theirs = encoder(&teacher, "t.safetensors");
    assert!(theirs.len() > 10);
    assert_eq!(theirs, encoder(&after, "a.safetensors"));
    // The head learns the teacher's scores: nearer them after the steps than at its start.
    let want = fingerprint(&teacher, &set);
    let distance = |n: &Network| {
        let got = fingerprint(n, &set);
        assert_eq!(got.len(), want.len());
        got.iter()
            .zip(&want)
            .map(|(g, w)| (g - w).powi(2))
            .sum::<f32>()
            / got.len() as f32
    };
    let (d0, d1) = (distance(&before), distance(&after));
    assert!(
        d1 < 0.5 * d0,
        "distance to the teacher's scores: {d0} at the start, {d1} after"
    );
    // Trained on from the student's weights (a warm restart at learning rate 0): its head is
    // the student's, its encoder still the teacher's.
    let student_file = files.path().join("student.safetensors");
    let warm = TrainConfig {
        init: Some(alignist::train::config::InitWeights {
            path: student_file.display().to_string(),
            file: alignist::bundle::save_weights(&after, &student_file).unwrap(),
            trained_by: "the test's student".into(),
            image_size: None,
            layout: None,
            pool_grid: None,
        }),
        ..student(0.0)
    };
    let (again, _) = go(&warm).unwrap();
    assert_eq!(theirs, encoder(&again, "w.safetensors"));
    assert_eq!(fingerprint(&again, &set), fingerprint(&after, &set));
    // A teacher whose encoder is not the run's, or whose file is not the recorded one, is refused
    // with its path named.
    let mut other = student(3e-3);
    other.network = other.network.with_image_size(SIZE * 2);
    let err = go(&other).unwrap_err().to_string();
    assert!(
        err.contains("network.safetensors") && err.contains("px"),
        "{err}"
    );
    let mut other = student(3e-3);
    other.teacher.as_mut().unwrap().file.sha256 = "0".repeat(64);
    let err = go(&other).unwrap_err().to_string();
    assert!(err.contains("network.safetensors"), "{err}");
}

/// `encoder_lr_scale`: one Adam step moves every encoder parameter by that share of what the
/// same step moves it at the head's rate, and the head exactly as before.
#[test]
fn the_encoder_learns_at_its_own_share_of_the_learning_rate() {
    let set = tiny_set();
    let cfg = TrainConfig {
        steps: 1,
        warmup: 1,
        ..config(alignist_method())
    };
    let files = tempfile::tempdir().unwrap();
    let weights = |c: &TrainConfig, name: &str| {
        let (n, _) = train(c, &set, None, false, |_, _, _| ControlFlow::Continue(())).unwrap();
        let p = files.path().join(name);
        alignist::bundle::save_weights(&n, &p).unwrap();
        let mut t = tensors(&p);
        t.retain(|k, _| !k.contains("running"));
        t
    };
    let start = weights(
        &TrainConfig {
            lr: 0.0,
            ..cfg.clone()
        },
        "start.safetensors",
    );
    let same = weights(&cfg, "same.safetensors");
    let scaled = weights(
        &TrainConfig {
            encoder_lr_scale: Some(0.1),
            contrast: None,
            target_temperature: None,
            ..cfg.clone()
        },
        "scaled.safetensors",
    );
    let (mut encoder, mut head) = (0, 0);
    for (name, s) in &start {
        let floats = |b: &[u8]| -> Vec<f32> {
            b.chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                .collect()
        };
        let moved = |w: &std::collections::BTreeMap<String, Vec<u8>>| -> f64 {
            floats(&w[name])
                .iter()
                .zip(floats(s))
                .map(|(a, b)| (a - b).abs() as f64)
                .fold(0.0, f64::max)
        };
        let (full, part) = (moved(&same), moved(&scaled));
        if name.starts_with("encoder.") {
            encoder += 1;
            assert!(full > 0.0, "{name} did not move");
            assert!(
                (part / full - 0.1).abs() < 0.01,
                "{name}: moved {part} at 0.1 × the rate, {full} at the rate"
            );
        } else {
            head += 1;
            assert!(
                (part - full).abs() <= 1e-6 * full.max(1e-12),
                "{name}: the head moved {part} against {full}"
            );
        }
    }
    assert!(
        encoder > 5 && head > 2,
        "{encoder} encoder, {head} head tensors"
    );
}

/// The contrast term (`TrainConfig::contrast`): the first step scores the same batch, so its loss
/// is the paper's plus the term, which is positive for an untrained network; the run trains other
/// weights than the paper's loss alone.
#[test]
fn a_contrast_term_adds_to_the_papers_loss_and_trains_other_weights() {
    let set = tiny_set();
    let run = |cfg: &TrainConfig| {
        let mut losses = Vec::new();
        let (network, _) = train(cfg, &set, None, false, |_, _, l| {
            losses.push(l);
            ControlFlow::Continue(())
        })
        .unwrap();
        (network, losses)
    };
    let (paper, paper_losses) = run(&config(alignist_method()));
    let (with, with_losses) = run(&TrainConfig {
        contrast: Some(1.0),
        ..config(alignist_method())
    });
    assert!(
        with_losses[0] > paper_losses[0] + 1e-3,
        "first step: {} with the term, {} without",
        with_losses[0],
        paper_losses[0]
    );
    assert!(with_losses.iter().all(|l| l.is_finite()), "{with_losses:?}");
    assert_ne!(fingerprint(&paper, &set), fingerprint(&with, &set));
}

/// Tempered targets (`TrainConfig::target_temperature`): the temperature starts at T₀, is its
/// square root halfway and 1 at the last step (1 throughout without one); a run with them trains
/// other weights than the paper's targets.
#[test]
fn tempered_targets_anneal_to_the_papers_and_train_other_weights() {
    let tempered = TrainConfig {
        target_temperature: Some(25.0),
        ..config(alignist_method())
    };
    assert_eq!(tempered.target_temperature_at(0, 100), 25.0);
    assert!((tempered.target_temperature_at(50, 100) - 5.0).abs() < 1e-9);
    assert_eq!(tempered.target_temperature_at(100, 100), 1.0);
    let paper = config(alignist_method());
    assert_eq!(paper.target_temperature_at(0, 100), 1.0);
    let set = tiny_set();
    let run = |cfg: &TrainConfig| {
        train(cfg, &set, None, false, |_, _, _| ControlFlow::Continue(()))
            .unwrap()
            .0
    };
    assert_ne!(
        fingerprint(&run(&paper), &set),
        fingerprint(&run(&tempered), &set)
    );
}
