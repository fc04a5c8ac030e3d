//! The nested grid: sizes, exact cells, nesting, equal volumes, the reference centres, the CLI.

use alignist::so3::{
    GridLevel, covering_radius, geodesic_angle, haar_rotations, jitter_in_cell, quaternion_angle,
    to_quaternion,
};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// `n` rotations `Rz(φ)·Ry(θ)·Rz(ψ)` whose z axis lies within 1° of the north pole, and `n`
/// within 1° of the south pole.
fn near_poles(r: &mut ChaCha8Rng, n: usize) -> Vec<nalgebra::Rotation3<f64>> {
    use nalgebra::{Rotation3, Vector3};
    let mut out = Vec::new();
    for north in [true, false] {
        for _ in 0..n {
            let theta = r.random_range(0.0..1f64.to_radians());
            let theta = if north {
                theta
            } else {
                std::f64::consts::PI - theta
            };
            let (phi, psi) = (
                r.random_range(0.0..std::f64::consts::TAU),
                r.random_range(0.0..std::f64::consts::TAU),
            );
            out.push(
                Rotation3::from_axis_angle(&Vector3::z_axis(), phi)
                    * Rotation3::from_axis_angle(&Vector3::y_axis(), theta)
                    * Rotation3::from_axis_angle(&Vector3::z_axis(), psi),
            );
        }
    }
    out
}

#[test]
fn every_centre_lies_in_its_own_cell() {
    for level in 0..=3u8 {
        let g = GridLevel::new(level).unwrap();
        assert_eq!(g.len(), 72 * 8usize.pow(level as u32));
        for i in 0..g.len() as u64 {
            assert_eq!(g.cell_of(&g.rotation(i)), i, "level {level}");
        }
    }
    let mut r = rng(1);
    for level in 4..=5u8 {
        let g = GridLevel::new(level).unwrap();
        for _ in 0..20_000 {
            let i = r.random_range(0..g.len() as u64);
            assert_eq!(g.cell_of(&g.rotation(i)), i, "level {level}");
        }
    }
    assert_eq!(GridLevel::new(6).unwrap().len(), 72 * 8usize.pow(6));
}

#[test]
fn rotations_jittered_inside_a_cell_map_back_to_it() {
    let mut r = rng(2);
    for level in 0..=4u8 {
        let g = GridLevel::new(level).unwrap();
        for _ in 0..300 {
            let i = r.random_range(0..g.len() as u64);
            for _ in 0..10 {
                let j = jitter_in_cell(&g, i, &mut r);
                assert_eq!(g.cell_of(&j), i, "level {level}");
            }
        }
    }
}

#[test]
fn jitter_fills_the_cell_not_only_its_centre() {
    // Jittered samples must spread over the cell: their mean angle to the centre is a sizeable
    // fraction of the covering radius, and they reach near the cell's boundary.
    let g = GridLevel::new(2).unwrap();
    let mut r = rng(12);
    let i = 1234;
    let centre = g.rotation(i);
    let angles: Vec<f64> = (0..2000)
        .map(|_| geodesic_angle(&centre, &jitter_in_cell(&g, i, &mut r)))
        .collect();
    let mean = angles.iter().sum::<f64>() / angles.len() as f64;
    let max = angles.iter().cloned().fold(0.0, f64::max);
    assert!(mean > 0.4 * max, "mean {mean} max {max}");
    assert!(max.to_degrees() > 5.0, "max {}", max.to_degrees());
}

#[test]
fn cells_nest_exactly_across_levels() {
    let mut rots = haar_rotations(&mut rng(3), 10_000);
    rots.extend(near_poles(&mut rng(13), 2_000));
    let grids: Vec<GridLevel> = (0..=6).map(|l| GridLevel::new(l).unwrap()).collect();
    for level in 0..=5usize {
        for r in &rots {
            let coarse = grids[level].cell_of(r);
            let fine = grids[level + 1].cell_of(r);
            assert_eq!(grids[level + 1].parent(fine), Some(coarse));
            assert!(grids[level].children(coarse).contains(&fine));
        }
    }
}

#[test]
fn cells_have_equal_volume_chi_square() {
    let g = GridLevel::new(1).unwrap();
    let n = 200_000;
    let mut counts = vec![0u64; g.len()];
    for r in haar_rotations(&mut rng(4), n) {
        counts[g.cell_of(&r) as usize] += 1;
    }
    let expected = n as f64 / g.len() as f64;
    let chi2: f64 = counts
        .iter()
        .map(|&c| (c as f64 - expected).powi(2) / expected)
        .sum();
    let dof = (g.len() - 1) as f64;
    // chi² has mean dof and sd sqrt(2 dof) ≈ 34 here; 5 sd is p ≈ 1e-6.
    assert!(
        (chi2 - dof).abs() < 5.0 * (2.0 * dof).sqrt(),
        "chi² = {chi2} for {dof} dof"
    );
}

#[test]
fn the_same_test_rejects_unequal_cells() {
    // The chi-square check above can fail: assigning by nearest centre of a grid whose tilt
    // centres are shifted makes unequal cells and a huge chi².
    let g = GridLevel::new(0).unwrap();
    let centres: Vec<[f64; 4]> = (0..g.len() as u64)
        .map(|i| to_quaternion(&(g.rotation(i) * alignist::so3::rot_z(0.3 * (i % 3) as f64))))
        .collect();
    let n = 20_000;
    let mut counts = vec![0u64; g.len()];
    for r in haar_rotations(&mut rng(5), n) {
        let q = to_quaternion(&r);
        let best = (0..centres.len())
            .min_by(|&a, &b| {
                quaternion_angle(&q, &centres[a]).total_cmp(&quaternion_angle(&q, &centres[b]))
            })
            .unwrap();
        counts[best] += 1;
    }
    let expected = n as f64 / g.len() as f64;
    let chi2: f64 = counts
        .iter()
        .map(|&c| (c as f64 - expected).powi(2) / expected)
        .sum();
    let dof = (g.len() - 1) as f64;
    assert!(chi2 - dof > 5.0 * (2.0 * dof).sqrt(), "chi² = {chi2}");
}

#[test]
fn every_rotation_lies_within_the_covering_radius() {
    // The covering radius is the largest angle from a rotation to its cell's centre. Haar-random
    // rotations, plus rotations whose z axis lies within 1° of either pole (where plain ZYZ cells
    // were slivers ~90° long), at every level.
    let mut rots = haar_rotations(&mut rng(6), 50_000);
    rots.extend(near_poles(&mut rng(7), 20_000));
    // Exactly at the poles too.
    rots.push(nalgebra::Rotation3::from_axis_angle(
        &nalgebra::Vector3::z_axis(),
        1.0,
    ));
    rots.push(
        nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::y_axis(), std::f64::consts::PI)
            * nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), 1.0),
    );
    let mut radii = Vec::new();
    for level in 0..=6u8 {
        let g = GridLevel::new(level).unwrap();
        let worst = rots
            .iter()
            .map(|r| geodesic_angle(r, &g.rotation(g.cell_of(r))))
            .fold(0.0f64, f64::max);
        radii.push(worst.to_degrees());
        assert!(
            worst <= covering_radius(level),
            "level {level}: {:.2}° > {:.2}°",
            worst.to_degrees(),
            covering_radius(level).to_degrees()
        );
        // And the bound is not loose: the worst case comes within 30 % of it.
        assert!(
            worst > 0.7 * covering_radius(level),
            "level {level}: {radii:?}"
        );
    }
    eprintln!("worst angle to the cell centre per level (deg): {radii:?}");
}

#[test]
fn polar_cells_are_compact_and_old_centres_stay_readable() {
    // The old convention (plain ψ) differs only in the polar caps: equatorial cells keep their
    // centres, and a polar cell's centre keeps its z axis.
    let g = GridLevel::new(2).unwrap();
    let per_base = g.len() as u64 / 12;
    for i in (0..g.len() as u64).step_by(7) {
        let (new, old) = (g.rotation(i), g.legacy_rotation(i));
        let base = i / per_base;
        if (4..8).contains(&base) {
            assert!(geodesic_angle(&new, &old) < 1e-12, "cell {i}");
        }
        let (zn, zo) = (new * nalgebra::Vector3::z(), old * nalgebra::Vector3::z());
        assert!((zn - zo).norm() < 1e-12, "cell {i}");
    }
}

/// The reference centres (healpy, from the definition in docs/DESIGN.md §1).
fn reference(level: u8) -> Vec<[f64; 4]> {
    let text = std::fs::read_to_string(format!(
        "{}/tests/data/so3-grid-level{level}.csv",
        env!("CARGO_MANIFEST_DIR")
    ))
    .unwrap();
    text.lines()
        .skip(1)
        .enumerate()
        .map(|(i, line)| {
            let f: Vec<f64> = line.split(',').map(|v| v.parse().unwrap()).collect();
            assert_eq!(f[0] as usize, i);
            [f[1], f[2], f[3], f[4]]
        })
        .collect()
}

#[test]
fn centres_match_the_healpy_reference() {
    for level in [1u8, 2] {
        let g = GridLevel::new(level).unwrap();
        let refs = reference(level);
        assert_eq!(refs.len(), g.len());
        for (i, q) in refs.iter().enumerate() {
            // The reference is IPDF's construction (plain ψ tilt): our legacy centres.
            let ours = to_quaternion(&g.legacy_rotation(i as u64));
            assert!(quaternion_angle(&ours, q) < 1e-6, "level {level} cell {i}");
        }
    }
}

#[test]
fn grid_cli_writes_the_centres_and_refuses_level_7() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("level1.csv");
    let exe = env!("CARGO_BIN_EXE_alignist-train");
    let status = std::process::Command::new(exe)
        .args(["grid", "--level", "1", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(status.status.success(), "{status:?}");
    let text = std::fs::read_to_string(&out).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("index,qw,qx,qy,qz"));
    let g = GridLevel::new(1).unwrap();
    let refs = g.quaternions();
    let rows: Vec<&str> = lines.collect();
    assert_eq!(rows.len(), refs.len());
    for (row, q) in rows.iter().zip(&refs) {
        let f: Vec<f64> = row.split(',').map(|v| v.parse().unwrap()).collect();
        assert!(f[1] >= 0.0);
        assert!(quaternion_angle(&[f[1], f[2], f[3], f[4]], q) < 1e-6);
    }

    let bad = std::process::Command::new(exe)
        .args(["grid", "--level", "7", "--out"])
        .arg(dir.path().join("level7.csv"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("--level 7") && err.contains("maximum"),
        "{err}"
    );
    assert!(!dir.path().join("level7.csv").exists());

    let unwritable = std::process::Command::new(exe)
        .args(["grid", "--level", "0", "--out", "/nonexistent-dir/x.csv"])
        .output()
        .unwrap();
    assert!(!unwritable.status.success());
    assert!(String::from_utf8_lossy(&unwritable.stderr).contains("/nonexistent-dir"));
}
