//! The CAD experts: fit of the SDF expert, symmetry-awareness of the features, the targets they
//! give, and their files. Each object's experts are trained once (default settings) per run and
//! shared by the tests through their files on disk.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::LazyLock;

use alignist::bundle::experts::ExpertSet;
use alignist::cad::Shape;
use alignist::experts::feature::{FeatureTrainConfig, symmetry_ratio};
use alignist::experts::modes::ModeTableConfig;
use alignist::experts::sdf::SdfTrainConfig;
use alignist::experts::select::WidthCriterion;
use alignist::experts::select::visible_points_at;
use alignist::so3::{
    GridLevel, SymmetryGroup, equivalents, geodesic_angle, haar_rotation, to_row_major_f32,
};
use alignist::train::experts::{ExpertsJob, train_expert_set};
use nalgebra::{Rotation3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Trains the default expert set of `shape` into a temporary folder (kept for the whole run).
fn trained(shape: Shape) -> PathBuf {
    let dir = tempfile::Builder::new()
        .prefix("experts")
        .tempdir()
        .unwrap()
        .keep();
    let (mesh, normalisation) = shape.mesh().normalised();
    let started = std::time::Instant::now();
    let mut set = train_expert_set(
        ExpertsJob {
            name: shape.name().into(),
            mesh,
            normalisation,
            symmetries: shape.symmetries(),
            sdf: SdfTrainConfig::default(),
            features: FeatureTrainConfig::default(),
            bake_resolution: 64,
            energy: Default::default(),
            width: Default::default(),
            modes: Default::default(),
            command: format!("tests/experts.rs trained({shape})"),
        },
        &mut |_, _, _, _| {},
    )
    .unwrap();
    set.save(&dir).unwrap();
    eprintln!(
        "{shape}: trained in {:.0} s: {}",
        started.elapsed().as_secs_f64(),
        std::fs::read_to_string(dir.join("manifest.json")).unwrap()
    );
    dir
}

static CUBE: LazyLock<PathBuf> = LazyLock::new(|| trained(Shape::Cube));
static TET_X: LazyLock<PathBuf> = LazyLock::new(|| trained(Shape::TetX));

fn load(dir: &Path) -> ExpertSet {
    ExpertSet::load(dir).unwrap()
}

#[test]
fn sdf_expert_fits_within_two_percent_of_the_radius() {
    let set = load(&CUBE);
    let fit = set.manifest.sdf.fit;
    assert!(fit.mae_near_surface < 0.02, "{fit:?}");
    assert!(fit.sign_accuracy_off_surface > 0.99, "{fit:?}");
    // The bake stays close to the network.
    assert!(
        set.manifest.bake.sdf_mean_error < 0.01,
        "{:?}",
        set.manifest.bake
    );
}

#[test]
fn cube_keys_are_symmetry_aware() {
    let set = load(&CUBE);
    let device = alignist::backend::device();
    let ratio = symmetry_ratio(&set.keys, &set.mesh, &set.symmetries(), None, 99, &device);
    assert!(ratio <= 0.25, "symmetric/random key distance ratio {ratio}");
    assert!((set.manifest.features.fit.symmetry_ratio - ratio).abs() < 0.1);
}

/// The faces of the tetX mesh that carry the marker.
fn marked_faces(set: &ExpertSet) -> Vec<u32> {
    match &set.mesh.colors {
        Some(alignist::cad::MeshColors::PerFace(c)) => (0..c.len() as u32)
            .filter(|&f| c[f as usize] == alignist::cad::shapes::MARKER_COLOR)
            .collect(),
        other => panic!("tetX has per-face colours, got {other:?}"),
    }
}

/// The rotations of T that move tetX's marked face onto another face.
fn marker_breaking(set: &ExpertSet) -> Vec<Rotation3<f64>> {
    let own = set.symmetries();
    SymmetryGroup::Tetrahedral
        .rotations()
        .into_iter()
        .filter(|s| !own.iter().any(|o| geodesic_angle(o, s) < 1e-6))
        .collect()
}

#[test]
fn tetx_keys_keep_the_marked_face_apart() {
    let set = load(&TET_X);
    let faces = marked_faces(&set);
    assert_eq!(faces.len(), 1);
    let device = alignist::backend::device();
    let breaking = marker_breaking(&set);
    assert_eq!(breaking.len(), 9);
    let mut with_identity = vec![Rotation3::identity()];
    with_identity.extend(breaking);
    let ratio = symmetry_ratio(
        &set.keys,
        &set.mesh,
        &with_identity,
        Some(&faces),
        7,
        &device,
    );
    assert!(
        ratio >= 0.5,
        "marked face vs its images on other faces: ratio {ratio}"
    );
}

#[test]
fn cube_targets_rank_every_equivalent_on_top() {
    let set = load(&CUBE);
    let baked = set.bake();
    let grid = GridLevel::new(3).unwrap();
    let cells = grid.matrices_f32();
    for seed in [1u64, 2] {
        let r_gt = haar_rotation(&mut ChaCha8Rng::seed_from_u64(seed));
        let x0 = visible_points_at(&set.mesh, &r_gt, seed);
        let total = baked.log_targets(&r_gt, &x0, &cells).combined();
        let eq = equivalents(&r_gt, &SymmetryGroup::Octahedral.rotations());
        let mut sorted = total.clone();
        sorted.sort_by(|a, b| b.total_cmp(a));
        let top1 = sorted[grid.len() / 100];
        // The exact equivalents score better than every rotation far from all of them.
        let at_eq = baked.log_targets(
            &r_gt,
            &x0,
            &eq.iter().map(to_row_major_f32).collect::<Vec<_>>(),
        );
        let eq_scores = at_eq.combined();
        let worst_equivalent = eq_scores.iter().cloned().fold(f32::INFINITY, f32::min);
        for e in &eq {
            let cell = grid.cell_of(e) as usize;
            assert!(
                total[cell] >= top1,
                "seed {seed}: equivalent's cell {} below the top 1 % ({top1})",
                total[cell]
            );
        }
        let mut far_best = f32::NEG_INFINITY;
        for i in 0..grid.len() as u64 {
            let r = grid.rotation(i);
            if eq
                .iter()
                .all(|e| geodesic_angle(e, &r) > 20f64.to_radians())
            {
                far_best = far_best.max(total[i as usize]);
            }
        }
        assert!(
            far_best < worst_equivalent,
            "seed {seed}: a far rotation scores {far_best} ≥ {worst_equivalent}"
        );
    }
}

#[test]
fn tetx_feature_targets_keep_only_the_marker_equivalents() {
    let set = load(&TET_X);
    let baked = set.bake();
    // Poses that show the marked face (the face x + y + z = −1/√3·|x| of the NOCS tetrahedron,
    // whose inradius is 1/3): at least 30 % of the visible points on it.
    let showing: Vec<u64> = (0u64..200)
        .filter(|&seed| {
            let r_gt = haar_rotation(&mut ChaCha8Rng::seed_from_u64(seed));
            let x0 = visible_points_at(&set.mesh, &r_gt, seed);
            let on = x0
                .iter()
                .filter(|p| (p.x + p.y + p.z) / 3f32.sqrt() < -0.3)
                .count();
            on * 10 >= x0.len() * 3
        })
        .take(2)
        .collect();
    assert_eq!(showing.len(), 2);
    for seed in showing {
        let r_gt = haar_rotation(&mut ChaCha8Rng::seed_from_u64(seed));
        let x0 = visible_points_at(&set.mesh, &r_gt, seed);
        let allowed: Vec<[f32; 9]> = equivalents(&r_gt, &set.symmetries())
            .iter()
            .map(to_row_major_f32)
            .collect();
        let other: Vec<[f32; 9]> = equivalents(&r_gt, &marker_breaking(&set))
            .iter()
            .map(to_row_major_f32)
            .collect();
        let a = baked.log_targets(&r_gt, &x0, &allowed);
        let o = baked.log_targets(&r_gt, &x0, &other);
        // The shape expert cannot tell them apart; the feature expert can.
        let worst_allowed = a.log_a_se.iter().cloned().fold(f32::INFINITY, f32::min);
        let best_other = o.log_a_se.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
        let spread_sdf = a
            .log_a_sdf
            .iter()
            .chain(&o.log_a_sdf)
            .fold(0f32, |m, v| m.max(v.abs()));
        assert!(
            spread_sdf < 0.05 * set.manifest.energy.lambda_sdf as f32,
            "sdf sees all 12 alike"
        );
        assert!(
            worst_allowed > best_other,
            "seed {seed}: allowed {:?} vs other {:?}",
            a.log_a_se,
            o.log_a_se
        );
    }
}

fn train_cli(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_alignist-train"))
        .args(args)
        .output()
        .unwrap()
}

/// `alignist-train experts` on a SYMSOL shape at tiny sizes — `[SDF steps, feature steps, views
/// (renders per feature step and views of the mode table), bake resolution]` — into `out`;
/// succeeds or shows why not.
fn tiny_experts_cli(shape: &str, sizes: [&str; 4], out: &Path) -> Output {
    let [steps, feature_steps, views, bake] = sizes;
    let out = train_cli(&[
        "experts",
        "--shape",
        shape,
        "--steps",
        steps,
        "--feature-steps",
        feature_steps,
        "--images",
        views,
        "--bake-resolution",
        bake,
        "--table-views",
        views,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// `alignist-train score` of the expert set at `set_dir` for `rotation`, at level 1, into `csv`.
fn score_cli(set_dir: &Path, rotation: &str, csv: &Path) -> Output {
    train_cli(&[
        "score",
        "--experts",
        set_dir.to_str().unwrap(),
        "--rotation",
        rotation,
        "--level",
        "1",
        "--out",
        csv.to_str().unwrap(),
    ])
}

#[test]
fn experts_and_score_cli_write_files_that_load_and_refuse_corruption() {
    let dir = tempfile::tempdir().unwrap();
    let set_dir = dir.path().join("cube_experts");
    let out = tiny_experts_cli("cube", ["20", "5", "2", "16"], &set_dir);
    let report = String::from_utf8_lossy(&out.stderr);
    assert!(
        report.contains("SDF: MAE") && report.contains("lambda_sdf"),
        "{report}"
    );
    for f in [
        "manifest.json",
        "mesh.ply",
        "modes.json",
        "sdf.safetensors",
        "keys.safetensors",
        "query.safetensors",
    ] {
        assert!(set_dir.join(f).exists(), "{f}");
    }
    let csv = dir.path().join("targets.csv");
    let out = score_cli(&set_dir, "0.5,0.5,-0.5,0.5", &csv);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = std::fs::read_to_string(&csv).unwrap();
    let rows: Vec<&str> = text.lines().collect();
    assert_eq!(rows[0], "index,log_a_sdf,log_a_se");
    assert_eq!(rows.len(), 577);
    for (i, row) in rows[1..].iter().enumerate() {
        let f: Vec<f64> = row.split(',').map(|v| v.parse().unwrap()).collect();
        assert_eq!(f[0] as usize, i);
        assert!(f[1] <= 0.0 && f[2] <= 0.0 && f[1].is_finite() && f[2].is_finite());
    }
    let bad_rotation = score_cli(&set_dir, "1,0,0", &csv);
    assert!(!bad_rotation.status.success());
    assert!(String::from_utf8_lossy(&bad_rotation.stderr).contains("--rotation"));

    // A corrupted weight file is refused, naming it.
    let keys = set_dir.join("keys.safetensors");
    let mut bytes = std::fs::read(&keys).unwrap();
    let n = bytes.len();
    bytes[n - 5] ^= 0x55;
    std::fs::write(&keys, &bytes).unwrap();
    let err = ExpertSet::load(&set_dir)
        .err()
        .expect("corrupt keys refused")
        .to_string();
    assert!(
        err.contains("keys.safetensors") && err.contains("sha256"),
        "{err}"
    );
    let out = score_cli(&set_dir, "1,0,0,0", &csv);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("keys.safetensors"));
}

#[test]
fn mismatched_manifests_are_refused_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let set_dir = dir.path().join("x");
    tiny_experts_cli("tet", ["5", "2", "1", "8"], &set_dir);
    let manifest = set_dir.join("manifest.json");
    let original = std::fs::read_to_string(&manifest).unwrap();
    let edit = |from: &str, to: &str| {
        assert!(original.contains(from), "{from}");
        std::fs::write(&manifest, original.replacen(from, to, 1)).unwrap();
        ExpertSet::load(&set_dir)
            .err()
            .expect("refused")
            .to_string()
    };
    // The SDF network described with another width: the weights no longer fit.
    let err = edit("\"hidden\": 256", "\"hidden\": 128");
    assert!(err.contains("sdf.safetensors"), "{err}");
    let err = edit("\"format_version\": 2", "\"format_version\": 9");
    assert!(
        err.contains("manifest.json") && err.contains("format_version"),
        "{err}"
    );
    let err = edit("\"sdf\": {", "\"sdf_renamed\": {");
    assert!(
        err.contains("manifest.json") && err.contains("sdf"),
        "{err}"
    );
    std::fs::write(&manifest, &original).unwrap();
    assert!(ExpertSet::load(&set_dir).is_ok());
}

/// A tiny expert job (seconds) whose symmetries are `symmetries`.
fn tiny_job(symmetries: Vec<Rotation3<f64>>) -> ExpertsJob {
    let (mesh, normalisation) = Shape::Cube.mesh().normalised();
    ExpertsJob {
        name: "cube".into(),
        mesh,
        normalisation,
        symmetries,
        sdf: SdfTrainConfig {
            steps: 20,
            ..Default::default()
        },
        features: FeatureTrainConfig {
            steps: 4,
            images: 2,
            ..Default::default()
        },
        bake_resolution: 16,
        energy: Default::default(),
        width: WidthCriterion {
            poses: 2,
            axes: 4,
            ..Default::default()
        },
        modes: ModeTableConfig {
            views: 2,
            coarse_level: 1,
            level: 2,
            keep_fraction: 0.02,
            seed: 0,
        },
        command: "tiny".into(),
    }
}

#[test]
fn lambda_selection_and_mode_table_never_read_the_symmetry_group() {
    let right = train_expert_set(tiny_job(Shape::Cube.symmetries()), &mut |_, _, _, _| {}).unwrap();
    // A wrong group (C5 is no symmetry of the cube) and no group at all.
    for wrong in [
        SymmetryGroup::Cyclic(5).rotations(),
        vec![Rotation3::identity()],
    ] {
        let other = train_expert_set(tiny_job(wrong), &mut |_, _, _, _| {}).unwrap();
        assert_eq!(other.manifest.energy, right.manifest.energy);
        assert_eq!(
            other.manifest.energy_selection,
            right.manifest.energy_selection
        );
        assert_eq!(other.modes, right.modes);
    }
    let selection = &right.manifest.energy_selection;
    assert_eq!(selection.criterion, "width");
    assert!(right.manifest.energy.lambda_sdf > 0.0 && right.manifest.energy.lambda_se > 0.0);
    // By construction each expert's log-target falls by ¼ at the width.
    let at_width = selection.profile[1];
    assert!((at_width.1 + 0.25).abs() < 1e-9 && (at_width.2 + 0.25).abs() < 1e-9);
}

#[test]
fn cube_mode_table_holds_every_symmetry_and_sampling_reaches_every_equivalent() {
    use alignist::train::{ModeSampler, SamplingStrategy, sample_rotations};
    let set = load(&CUBE);
    let table = set.modes.clone().expect("a format-2 set has its table");
    let grid = table.grid().unwrap();
    let group = SymmetryGroup::Octahedral.rotations();
    for s in &group {
        // A cell whose centre is within 6° of the symmetry. The cube's symmetries sit on cell
        // boundaries of the grid (their tilts are multiples of 90°, edges of the 7.5° tilt bins
        // of level 4; 8 have their z axis at a pole, where cells are slivers), so the nearest
        // centres are 3.0–3.5° away (measured on the default cube experts), not `cell_of`'s.
        let nearest = table
            .cells
            .iter()
            .map(|&c| geodesic_angle(&grid.rotation(c), s))
            .fold(f64::INFINITY, f64::min);
        assert!(
            nearest < 6f64.to_radians(),
            "symmetry {s:?}: the nearest table cell is {:.1}° away",
            nearest.to_degrees()
        );
    }
    let sampler = ModeSampler::new(&table, 0.0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(404);
    let r_gt = haar_rotation(&mut rng);
    let samples = sample_rotations(
        &SamplingStrategy::ModeFocused {
            focused: 2000,
            temperature: 0.0,
            focused_end: None,
            twin_share: 0.0,
            own_twins: None,
        },
        2001,
        &r_gt,
        Some(&sampler),
        &mut rng,
    );
    for e in equivalents(&r_gt, &group) {
        let hits = samples[1..]
            .iter()
            .filter(|r| geodesic_angle(r, &e) < 8f64.to_radians())
            .count();
        // ~30 for most equivalents, ~10 for the 8 whose relative rotation has its z axis at a
        // pole (the table holds 16 cells within 8° of those against 44: polar cells are slivers).
        assert!(
            hits >= 3,
            "{hits} of 2000 samples within 8° of an equivalent"
        );
    }
}

#[test]
fn twin_sampling_draws_its_share_around_the_twins_and_none_without() {
    use alignist::train::{ModeSampler, SamplingStrategy, sample_rotations};
    let set = load(&CUBE);
    let table = set.modes.clone().expect("a format-2 set has its table");
    // A turn as far from every symmetry of the cube as a rotation gets: 62.8°.
    let axis = nalgebra::Unit::new_normalize(Vector3::new(1.0, 1.0, 0.0));
    let twin = Rotation3::from_axis_angle(&axis, 90f64.to_radians());
    let group = SymmetryGroup::Octahedral.rotations();
    let mut rng = ChaCha8Rng::seed_from_u64(405);
    let r_gt = haar_rotation(&mut rng);
    // The angle from `r` to the nearest of `centre·g`, g in the cube's group.
    let nearest = |r: &Rotation3<f64>, centre: &Rotation3<f64>| {
        group
            .iter()
            .map(|g| geodesic_angle(r, &(centre * g)))
            .fold(f64::INFINITY, f64::min)
    };
    let strategy = |share| SamplingStrategy::mode_focused_share(2001, 1.0).with_twin_share(share);
    // The share of focused samples nearer the twins than the truth's equivalents.
    let mut at_twins = |sampler: &ModeSampler, share| {
        let samples = sample_rotations(&strategy(share), 2001, &r_gt, Some(sampler), &mut rng);
        samples[1..]
            .iter()
            .filter(|r| nearest(r, &(r_gt * twin)) < nearest(r, &r_gt))
            .count() as f64
            / 2000.0
    };
    let sampler = ModeSampler::new(&table, 0.0)
        .unwrap()
        .with_twins(vec![twin]);
    let none = at_twins(&sampler, 0.0);
    let half = at_twins(&sampler, 0.5);
    let all = at_twins(&sampler, 1.0);
    assert!(none < 0.05 && all > 0.95, "{none} {all}");
    assert!((half - 0.5).abs() < 0.07, "{half}");
    // A sampler without twins ignores the share, and draws what it drew without one.
    let plain = ModeSampler::new(&table, 0.0).unwrap();
    let ignored = at_twins(&plain, 1.0);
    assert!(ignored < 0.05, "{ignored}");
    let draw = |share| {
        let mut rng = ChaCha8Rng::seed_from_u64(406);
        sample_rotations(&strategy(share), 2001, &r_gt, Some(&plain), &mut rng)
    };
    assert_eq!(draw(1.0), draw(0.0));
}

#[test]
fn a_near_symmetry_names_its_twins() {
    use alignist::experts::symmetry::NearSymmetry;
    let near = |label: &str| NearSymmetry {
        label: label.into(),
        axes: vec![[0.0, 1.0, 0.0]],
        residual: 0.03,
    };
    let c2 = near("C2").twins();
    assert_eq!(c2.len(), 1);
    let half_turn_about_y = Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI);
    assert!(geodesic_angle(&c2[0], &half_turn_about_y) < 1e-9);
    assert_eq!(near("D3").twins().len(), 2);
    let cone = near("cone").twins();
    assert_eq!(cone.len(), 35);
    assert!(
        cone.iter()
            .all(|r| (r.axis().unwrap().y.abs() - 1.0).abs() < 1e-9)
    );
    assert!(near("T").twins().is_empty() && near("none").twins().is_empty());
    let mut no_axis = near("C4");
    no_axis.axes.clear();
    assert!(no_axis.twins().is_empty());
}

#[test]
fn format_1_expert_sets_are_read_and_get_a_mode_table() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/symsol1/experts/cube");
    let set = ExpertSet::load(&dir).unwrap();
    if set.manifest.format_version != 1 {
        // The shipped model was retrained: make a format-1 copy of its set.
        let tmp = tempfile::tempdir().unwrap();
        let copy = tmp.path().join("cube");
        std::fs::create_dir_all(&copy).unwrap();
        for f in std::fs::read_dir(&dir).unwrap() {
            let f = f.unwrap();
            std::fs::copy(f.path(), copy.join(f.file_name())).unwrap();
        }
        let mut m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(copy.join("manifest.json")).unwrap())
                .unwrap();
        m["format_version"] = 1.into();
        m["files"].as_object_mut().unwrap().remove("modes.json");
        std::fs::write(copy.join("manifest.json"), m.to_string()).unwrap();
        return check_format_1(&copy);
    }
    check_format_1(&dir);
}

fn check_format_1(dir: &Path) {
    let set = ExpertSet::load(dir).unwrap();
    assert_eq!(set.manifest.format_version, 1);
    assert!(set.modes.is_none());
    let baked = set.bake();
    let table = set.mode_table(&baked).unwrap();
    assert!(table.validate().is_ok());
    assert_eq!(table.cells.len(), (294_912f64 * 0.01).ceil() as usize);
}
