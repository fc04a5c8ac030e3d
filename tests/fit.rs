//! The whole offline pipeline through the CLI, at tiny sizes: render → experts → fit (train,
//! checkpoint, evaluate, bundle) → eval → load, and a corrupt bundle refused.

mod common;

use std::path::Path;
use std::process::{Command, Output};

use alignist::bundle::model::ModelBundle;

fn run(args: &[&str]) -> Output {
    common::run_ok(env!("CARGO_BIN_EXE_alignist-train"), args)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The files of a tiny pipeline: renders of the cube (12 train, 3 test), its experts, a bundle.
struct Pipeline {
    dir: tempfile::TempDir,
    data: std::path::PathBuf,
    experts: std::path::PathBuf,
    bundle: std::path::PathBuf,
}

impl Pipeline {
    /// Renders the cube's data and trains its experts, at tiny sizes.
    fn prepare() -> Pipeline {
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("cube_data");
        let experts = dir.path().join("cube_experts");
        let bundle = dir.path().join("models/tiny");
        run(&[
            "render",
            "--shape",
            "cube",
            "--count",
            "12",
            "--size",
            "64",
            "--seed",
            "1",
            "--out",
            s(&data),
        ]);
        run(&[
            "render",
            "--shape",
            "cube",
            "--count",
            "3",
            "--size",
            "64",
            "--seed",
            "2",
            "--split",
            "test",
            "--out",
            s(&data),
        ]);
        common::tiny_cube_experts(&experts);
        Pipeline {
            dir,
            data,
            experts,
            bundle,
        }
    }

    /// `fit` of 4 steps (checkpoints every 2, evaluation at level 1) into `out`.
    fn fit_to(&self, out: &Path, extra: &[&str]) -> Output {
        let (data, experts) = (&self.data, &self.experts);
        let mut args = vec![
            "fit",
            "--data",
            s(data),
            "--experts",
            s(experts),
            "--out",
            s(out),
            "--steps",
            "4",
            "--batch",
            "2",
            "--k",
            "32",
            "--image-size",
            "32",
            "--checkpoint-every",
            "2",
            "--eval-level",
            "1",
            "--eval-images",
            "3",
        ];
        args.extend_from_slice(extra);
        run(&args)
    }

    /// `fit --fresh` of 2 steps (batch 2, K 16) of the cube's experts into `out`, its outcome
    /// returned as it is.
    fn fresh_fit(&self, out: &Path, extra: &[&str]) -> Output {
        Command::new(env!("CARGO_BIN_EXE_alignist-train"))
            .args([
                "fit",
                "--fresh",
                "--experts",
                s(&self.experts),
                "--out",
                s(out),
            ])
            .args(["--steps", "2", "--batch", "2", "--k", "16"])
            .args(extra)
            .output()
            .unwrap()
    }

    /// `fit` into the bundle.
    fn fit(&self, extra: &[&str]) -> Output {
        self.fit_to(&self.bundle, extra)
    }

    /// `eval` of the bundle on `images` test images at level 1: the overall figures.
    fn eval_overall(&self, images: &str) -> serde_json::Value {
        let (bundle, data) = (&self.bundle, &self.data);
        let report = self.dir.path().join("report.json");
        run(&[
            "eval",
            "--model",
            s(bundle),
            "--data",
            &format!("cube={}", s(data)),
            "--level",
            "1",
            "--images",
            images,
            "--out",
            s(&report),
        ]);
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        json["overall"].clone()
    }
}

#[test]
fn render_experts_fit_eval_and_load_a_bundle() {
    let p = Pipeline::prepare();
    let eval = a_fit_writes_its_bundle_with_its_evaluation(&p);
    resume_and_stop_at_finish_a_run(&p);
    assert_eq!(p.eval_overall("2")["images"], 2);
    fresh_renders_fit_with_their_loss_and_sampling(&p);
    a_warm_start_may_change_the_crop_side(&p);
    a_warm_start_may_grow_the_encoder(&p);
    a_narrower_head_is_distilled_from_a_bundle(&p);
    the_bundle_read_back_scores_as_fit_held_it(&p, &eval);
    bad_arguments_are_refused_naming_them(&p);
    a_corrupt_network_is_refused(&p);
}

/// `fit --fraction 0.5`: half the training images, its evaluation, its command and a checkpoint
/// on record. Returns the evaluation.
fn a_fit_writes_its_bundle_with_its_evaluation(
    p: &Pipeline,
) -> alignist::bundle::record::EvalReport {
    let bundle = &p.bundle;
    let out = p.fit(&["--fraction", "0.5"]);
    let report = String::from_utf8_lossy(&out.stderr);
    assert!(report.contains("6 training images"), "{report}");
    assert!(
        report.contains("evaluation at level 1") && report.contains("AR@30"),
        "{report}"
    );

    let loaded = ModelBundle::load(bundle).unwrap();
    let m = &loaded.manifest;
    assert_eq!(m.objects.len(), 1);
    assert_eq!(m.objects[0].name, "cube");
    assert_eq!(m.provenance.report.steps_run, 4);
    assert!(m.provenance.command.contains("--fraction 0.5"));
    let eval = m.evaluation.as_ref().unwrap();
    assert_eq!(eval.overall.images, 3);
    assert!(eval.overall.log_likelihood.is_finite());
    assert!(bundle.with_extension("checkpoints").join("latest").exists());

    eval.clone()
}

/// Resuming a finished run trains no more steps; `--stop-at` leaves a checkpoint and no bundle,
/// and `--resume` finishes the run from there.
fn resume_and_stop_at_finish_a_run(p: &Pipeline) {
    let (bundle, dir) = (&p.bundle, &p.dir);
    p.fit(&["--fraction", "0.5", "--resume"]);
    assert_eq!(
        ModelBundle::load(bundle)
            .unwrap()
            .manifest
            .provenance
            .report
            .steps_run,
        0
    );

    // A time-boxed part of a run: --stop-at leaves a checkpoint and no bundle; --resume
    // finishes the run from there.
    let parted = dir.path().join("parted");
    let out = p.fit_to(&parted, &["--stop-at", "2"]);
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("stopped at step 2 of 4"),
        "{out:?}"
    );
    assert!(!parted.join("manifest.json").exists());
    assert!(parted.with_extension("checkpoints").join("latest").exists());
    p.fit_to(&parted, &["--resume"]);
    let resumed = ModelBundle::load(&parted)
        .unwrap()
        .manifest
        .provenance
        .report;
    assert_eq!((resumed.resumed_from, resumed.steps_run), (2, 2));
}

/// Fresh renders instead of --data, with the L1 loss and half of K from the mode table.
fn fresh_renders_fit_with_their_loss_and_sampling(p: &Pipeline) {
    let (bundle, dir) = (&p.bundle, &p.dir);
    // Fresh renders instead of --data, with the L1 loss and half of K from the mode table: the
    // results table names each bundle's method as it was trained (it once printed
    // "alignist (GKL)" for every alignist bundle).
    let fresh = dir.path().join("fresh-l1");
    let out = p.fresh_fit(
        &fresh,
        &[
            "--loss",
            "l1",
            "--focused-fraction",
            "0.5",
            "--image-size",
            "32",
            "--eval-level",
            "1",
            "--eval-images",
            "4",
            "--profile",
        ],
    );
    assert!(out.status.success(), "{out:?}");
    assert!(String::from_utf8_lossy(&out.stdout).contains("step profile"));
    let fresh_manifest = ModelBundle::load(&fresh).unwrap().manifest;
    match fresh_manifest.provenance.train.method {
        alignist::train::Method::Alignist {
            sampling: alignist::train::SamplingStrategy::ModeFocused { focused, .. },
            ..
        } => assert_eq!(focused, 8, "half of K = 16"),
        other => panic!("{other:?}"),
    }
    let fresh_eval = fresh_manifest.evaluation.unwrap();
    assert_eq!(fresh_eval.overall.images, 4);
    assert_eq!(fresh_eval.chance_ar30.len(), 1);
    let table = run(&["results", s(bundle), s(&fresh)]);
    let table = String::from_utf8_lossy(&table.stdout);
    assert!(
        table.contains("alignist (GKL, mode-focused, cube PE)"),
        "{table}"
    );
    assert!(
        table.contains("alignist (L1, mode-focused 8 of 16, cube PE)"),
        "{table}"
    );
    assert!(table.contains("fresh renders"), "{table}");
    // The first mode's AR@30 closes every row of the metrics table: an evaluated share.
    assert!(table.contains("| median ° | first mode AR@30 |"), "{table}");
    let rows: Vec<&str> = table.lines().filter(|l| l.contains("| cube |")).collect();
    assert!(!rows.is_empty(), "{table}");
    for row in rows {
        let cells: Vec<&str> = row.trim_end_matches('|').split('|').collect();
        let share: f64 = cells.last().unwrap().trim().parse().unwrap();
        assert!((0.0..=1.0).contains(&share), "{row}");
    }
    eval_fresh_renders_its_own_crops(&fresh, &dir.path().join("report.json"));
}

/// `eval --fresh` renders its own test crops of every object of the bundle `fresh`; with
/// `--served` it also answers them as the server does; with `--realistic` it scores four sets.
fn eval_fresh_renders_its_own_crops(fresh: &Path, report: &Path) {
    let eval_fresh = |images: &str, extra: &[&str]| -> serde_json::Value {
        let args = [
            &["eval", "--model", s(fresh), "--fresh", "--images", images][..],
            extra,
            &["--level", "1", "--out", s(report)],
        ]
        .concat();
        run(&args);
        serde_json::from_str(&std::fs::read_to_string(report).unwrap()).unwrap()
    };
    let json = eval_fresh("3", &[]);
    assert_eq!(json["overall"]["images"], 3);
    assert!(json.get("served").is_none(), "{json}");
    // With --served: the same crops answered by the serving engine's search (calibrated on this
    // machine, as the server's default flags do), its top-1 and first mode scored per object and
    // overall.
    let json = eval_fresh("3", &["--served", "--top-k", "4"]);
    let served = &json["served"];
    assert_eq!(served["top_k"], 4, "{json}");
    assert_eq!(served["calibrated"], true, "{served}");
    assert_eq!(served["overall"]["images"], 3);
    assert_eq!(served["per_object"][0][0], "cube");
    assert_eq!(served["per_object"][0][1]["images"], 3);
    assert!(
        served["search"].as_str().unwrap().starts_with("start "),
        "{served}"
    );
    for key in ["top1_median_error_deg", "mode_median_error_deg"] {
        let e = served["overall"][key].as_f64().unwrap();
        assert!((0.0..=180.0).contains(&e), "{key} {e}");
    }
    assert!(served["search_p50_ms"].as_f64().unwrap() > 0.0);
    // With --realistic: clean renders, the held-out split's crops with exact and detector boxes,
    // and the training split's with exact boxes, one report each.
    let json = eval_fresh("2", &["--realistic"]);
    let sets: Vec<&str> = json
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["set"].as_str().unwrap())
        .collect();
    assert_eq!(
        sets,
        [
            "clean renders",
            "realistic (held-out split), exact boxes",
            "realistic, detector boxes",
            "realistic (training split), exact boxes"
        ]
    );
    for r in json.as_array().unwrap() {
        assert_eq!(r["report"]["overall"]["images"], 2, "{}", r["set"]);
        assert_eq!(r["report"]["images"].as_array().unwrap().len(), 2);
    }
    a_report_is_compared_image_by_image(report);
}

/// `compare`: a report against itself pairs every set with no difference; against the same
/// report with one image's argmax moved outside 30°, that image is counted on A's side; against
/// other crops, refused naming the set and the image.
fn a_report_is_compared_image_by_image(report: &Path) {
    let compare = |b: &Path| {
        Command::new(env!("CARGO_BIN_EXE_alignist-train"))
            .args(["compare", s(report), s(b)])
            .output()
            .unwrap()
    };
    let out = compare(report);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    assert_eq!(text.matches("(2 images)").count(), 4, "{text}");
    assert!(text.contains("+0.00 ± 0.00"), "{text}");
    let mut json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report).unwrap()).unwrap();
    let first = &mut json[1]["report"]["images"][0];
    let hit = first["argmax_error_deg"].as_f64().unwrap() < 30.0;
    first["argmax_error_deg"] = if hit { 90.0 } else { 10.0 }.into();
    let moved = report.with_extension("moved.json");
    std::fs::write(&moved, json.to_string()).unwrap();
    let text = String::from_utf8_lossy(&compare(&moved).stdout).to_string();
    let counted = if hit {
        "in A only 1, in B only 0"
    } else {
        "in A only 0, in B only 1"
    };
    assert!(text.contains(counted), "{text}");
    json[1]["report"]["images"][1]["object"] = "other".into();
    std::fs::write(&moved, json.to_string()).unwrap();
    let out = compare(&moved);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("realistic (held-out split)") && err.contains("image 1"),
        "{err}"
    );
}

/// `--init` from the 32 px bundle into a 48 px run: the encoder pools globally, so its weights
/// carry over, and the manifest records the side they were trained at. Another encoding is
/// refused, naming the bundle.
fn a_warm_start_may_change_the_crop_side(p: &Pipeline) {
    let (bundle, dir) = (&p.bundle, &p.dir);
    let warm = dir.path().join("warm-48");
    let fit = |encoding: &str| {
        let init = [
            "--init",
            s(bundle),
            "--image-size",
            "48",
            "--eval-images",
            "0",
        ];
        p.fresh_fit(&warm, &[&init[..], &["--encoding", encoding]].concat())
    };
    let out = fit("cube");
    assert!(out.status.success(), "{out:?}");
    let manifest = ModelBundle::load(&warm).unwrap().manifest;
    assert_eq!(manifest.network.image_size, 48);
    let init = manifest.provenance.train.init.unwrap();
    assert_eq!(init.image_size, Some(32));
    assert!(init.path.contains("models/tiny"), "{}", init.path);

    // A bundle's manifest and weights alone (as `training/warm-starts/` may keep them) start a
    // run too; the loader the server uses, which needs the experts, refuses such a folder.
    let weights_only = dir.path().join("weights-only");
    std::fs::create_dir_all(&weights_only).unwrap();
    for file in ["manifest.json", "network.safetensors"] {
        std::fs::copy(bundle.join(file), weights_only.join(file)).unwrap();
    }
    assert!(ModelBundle::load(&weights_only).is_err());
    let from_weights = dir.path().join("warm-from-weights");
    let args = ["--init", s(&weights_only), "--eval-images", "0"];
    let out = p.fresh_fit(&from_weights, &args);
    assert!(out.status.success(), "{out:?}");
    let init = ModelBundle::load(&from_weights)
        .unwrap()
        .manifest
        .provenance
        .train
        .init
        .unwrap();
    assert!(init.path.contains("weights-only"), "{}", init.path);
    // Weights that are not the ones the manifest names are refused, naming the file.
    std::fs::write(weights_only.join("network.safetensors"), b"not the weights").unwrap();
    let refused = p.fresh_fit(&from_weights, &args);
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains("network.safetensors"), "{err}");

    let refused = fit("ipdf");
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(
        err.contains("--init")
            && err.contains("models/tiny")
            && err.contains("image size may differ"),
        "{err}"
    );
}

/// `--init` into a layout with more blocks per stage, then more channels: the manifest records
/// the layout and grid grown from; a layout of another kind is refused.
fn a_warm_start_may_grow_the_encoder(p: &Pipeline) {
    let (bundle, dir) = (&p.bundle, &p.dir);
    // More blocks per stage from the tiny weights (here pooled over 2 × 2 cells at once).
    let deep = dir.path().join("warm-deep");
    let deepen = |layout: &str| {
        let args = [
            "--init",
            s(bundle),
            "--layout",
            layout,
            "--pool-grid",
            "2",
            "--eval-images",
            "0",
        ];
        p.fresh_fit(&deep, &args)
    };
    let out = deepen("tiny-deep");
    assert!(out.status.success(), "{out:?}");
    let manifest = ModelBundle::load(&deep).unwrap().manifest;
    assert_eq!(
        manifest.network.layout,
        alignist::net::ResNetLayout::TinyDeep
    );
    let init = manifest.provenance.train.init.unwrap();
    assert_eq!(init.layout, Some(alignist::net::ResNetLayout::Tiny));
    assert_eq!(init.pool_grid, Some(1));
    // Wider too, from that deep network and its grid: the added channels start unread, the head
    // reads their features once trained.
    let wide = dir.path().join("warm-wide");
    let args = [
        "--init",
        s(&deep),
        "--layout",
        "tiny-wide",
        "--pool-grid",
        "2",
        "--eval-images",
        "0",
    ];
    let out = p.fresh_fit(&wide, &args);
    assert!(out.status.success(), "{out:?}");
    let manifest = ModelBundle::load(&wide).unwrap().manifest;
    assert_eq!(
        manifest.network.layout,
        alignist::net::ResNetLayout::TinyWide
    );
    let init = manifest.provenance.train.init.unwrap();
    assert_eq!(init.layout, Some(alignist::net::ResNetLayout::TinyDeep));
    assert_eq!(init.pool_grid, None);
    let refused = deepen("resnet18");
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains("grows it"), "{err}");
}

/// `fit --teacher`: a head of its own width on the teacher's encoder, the teacher on record; a
/// teacher whose encoder is not the run's is refused, naming it.
fn a_narrower_head_is_distilled_from_a_bundle(p: &Pipeline) {
    let (bundle, dir) = (&p.bundle, &p.dir);
    let out = dir.path().join("distilled");
    let fit = |size: &str| {
        let args = [
            "--teacher",
            s(bundle),
            "--hidden",
            "16",
            "--image-size",
            size,
        ];
        p.fresh_fit(&out, &[&args[..], &["--eval-images", "0"]].concat())
    };
    let done = fit("32");
    assert!(done.status.success(), "{done:?}");
    let manifest = ModelBundle::load(&out).unwrap().manifest;
    assert_eq!(manifest.network.hidden, 16);
    let teacher = manifest.provenance.train.teacher.unwrap();
    assert!(teacher.path.contains("models/tiny"), "{}", teacher.path);
    assert_ne!(teacher.network.hidden, 16);
    let refused = fit("48");
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(
        err.contains("--teacher") && err.contains("models/tiny") && err.contains("px"),
        "{err}"
    );
}

/// The bundle read back scores as the network `fit` held in memory.
fn the_bundle_read_back_scores_as_fit_held_it(
    p: &Pipeline,
    eval: &alignist::bundle::record::EvalReport,
) {
    // The bundle read back scores as the network `fit` held in memory: evaluating the loaded
    // bundle on the same 3 test images at the same level reproduces the manifest's figures.
    let json = serde_json::json!({ "overall": p.eval_overall("3") });
    let again: alignist::so3::metrics::MetricsSummary =
        serde_json::from_value(json["overall"].clone()).unwrap();
    assert_eq!(again.images, eval.overall.images);
    assert_eq!(again.spread_deg, eval.overall.spread_deg);
    assert_eq!(again.median_error_deg, eval.overall.median_error_deg);
    assert_eq!(again.accuracy_at, eval.overall.accuracy_at);
    // LL sums logs over images and equivalents in a parallel reduction: equal up to the order of
    // the sum (the scores themselves are compared bit for bit in tests/train.rs).
    assert!((again.log_likelihood - eval.overall.log_likelihood).abs() < 1e-12);
}

/// `eval` of an object the bundle lacks, `fit` with a share above 1 and `fit` with a negative
/// learning rate are refused, naming them.
fn bad_arguments_are_refused_naming_them(p: &Pipeline) {
    let (bundle, data, experts, dir) = (&p.bundle, &p.data, &p.experts, &p.dir);
    let report = dir.path().join("report.json");
    let bad = Command::new(env!("CARGO_BIN_EXE_alignist-train"))
        .args([
            "eval",
            "--model",
            s(bundle),
            "--data",
            &format!("tet={}", s(data)),
            "--out",
            s(&report),
        ])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("no object 'tet'"));
    let bad = Command::new(env!("CARGO_BIN_EXE_alignist-train"))
        .args(["fit", "--fresh", "--experts", s(experts)])
        .args([
            "--out",
            s(&dir.path().join("never")),
            "--focused-fraction",
            "1.5",
        ])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(
        String::from_utf8_lossy(&bad.stderr).contains("--focused-fraction must be in [0, 1]"),
        "{}",
        String::from_utf8_lossy(&bad.stderr)
    );
    let bad = Command::new(env!("CARGO_BIN_EXE_alignist-train"))
        .args(["fit", "--fresh", "--experts", s(experts)])
        .args(["--out", s(&dir.path().join("never")), "--lr=-1e-3"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(
        stderr.contains("--lr") && stderr.contains("'-1e-3' is not a positive learning rate"),
        "{stderr}"
    );
    assert!(!dir.path().join("never").exists());
}

/// A corrupt network file is refused, naming it.
fn a_corrupt_network_is_refused(p: &Pipeline) {
    let bundle = &p.bundle;
    let weights = bundle.join("network.safetensors");
    let mut bytes = std::fs::read(&weights).unwrap();
    let n = bytes.len();
    bytes[n - 3] ^= 0x11;
    std::fs::write(&weights, bytes).unwrap();
    let err = ModelBundle::load(bundle)
        .err()
        .expect("refused")
        .to_string();
    assert!(
        err.contains("network.safetensors") && err.contains("sha256"),
        "{err}"
    );
}

/// `alignist-train calibrate` of `model` into `out` on 4 crops at level 2, with `extra` flags.
fn calibrate_tiny(model: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "calibrate",
        "--model",
        s(model),
        "--out",
        s(out),
        "--images",
        "4",
        "--level",
        "2",
        "--supersample",
        "1",
    ];
    args.extend_from_slice(extra);
    run(&args)
}

#[test]
fn calibrate_folds_a_recorded_temperature_into_a_new_bundle_and_refuses_twice() {
    let model = common::models_dir().join("tiny");
    let root = tempfile::tempdir().unwrap();
    let out = root.path().join("tiny-calibrated");
    let printed = calibrate_tiny(&model, &out, &["--eval-images", "2"]);
    let text = String::from_utf8_lossy(&printed.stdout);
    assert!(text.contains("temperature"), "{text}");
    let before = ModelBundle::load(&model).unwrap();
    let after = ModelBundle::load(&out).unwrap();
    let fit = after
        .manifest
        .calibration
        .clone()
        .expect("the calibration is recorded");
    assert!(fit.scale > 0.1 && fit.scale < 5.0, "{fit:?}");
    // The fitted scale never lowers the calibration crops' LL (scale 1 is one of the candidates
    // of a concave maximisation).
    assert!(fit.ll_after >= fit.ll_before - 1e-6, "{fit:?}");
    assert_eq!(fit.images, 4);
    assert!(fit.command.contains("calibrate"));
    let evaluation = after.manifest.evaluation.as_ref().unwrap();
    assert!(
        evaluation.images.is_empty(),
        "a manifest keeps the summaries only"
    );
    assert!(
        before.manifest.calibration.is_none(),
        "the input is left as it was"
    );
    // A calibrated bundle is not calibrated again.
    let again = Command::new(env!("CARGO_BIN_EXE_alignist-train"))
        .args(["calibrate", "--model", s(&out), "--out"])
        .arg(root.path().join("twice"))
        .output()
        .unwrap();
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("calibrated already"));
}

/// `calibrate --per-branch` records a factor per branch and folds each into its own branch: the
/// calibrated network's shape and feature log-weights are the input's times those factors.
#[test]
fn calibrate_per_branch_scales_each_branch_by_its_own_recorded_factor() {
    use alignist::net::{ProjectedGrid, images_tensor};
    let model = common::models_dir().join("tiny");
    let root = tempfile::tempdir().unwrap();
    let out = root.path().join("tiny-per-branch");
    let printed = calibrate_tiny(&model, &out, &["--per-branch", "--eval-images", "0"]);
    let text = String::from_utf8_lossy(&printed.stdout);
    assert!(text.contains("branch scales"), "{text}");
    let before = ModelBundle::load(&model).unwrap();
    let after = ModelBundle::load(&out).unwrap();
    let fit = after.manifest.calibration.clone().expect("recorded");
    let [shape, feature] = fit.branch_scales.expect("the branch scales are recorded");
    assert!(fit.ll_after >= fit.ll_before - 1e-6, "{fit:?}");
    let config = &before.manifest.network;
    let size = config.image_size as usize;
    let crop: Vec<u8> = (0..size * size * 3).map(|i| (i * 37 % 251) as u8).collect();
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv);
    let branches = |bundle: &ModelBundle| {
        let grid = ProjectedGrid::new(&bundle.network, config, 1).unwrap();
        let features = bundle
            .network
            .encoder
            .forward(images_tensor(&[&crop], size, &device));
        grid.branch_log_weights_of_features(features).remove(0)
    };
    let ((s0, f0), (s1, f1)) = (branches(&before), branches(&after));
    for (x0, x1, factor) in [(&s0, &s1, shape), (&f0, &f1, feature)] {
        for (a, b) in x0.iter().zip(x1) {
            assert!(
                (a * factor as f32 - b).abs() < 1e-3 * (1.0 + a.abs()),
                "{a} × {factor} ≠ {b}"
            );
        }
    }
}
