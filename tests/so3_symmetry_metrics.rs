//! Symmetry groups, equivalents, metrics and the encodings.

use alignist::encoding::{CUBE_ENCODING_DIM, RotationEncoding, cube_encoding, ipdf_encoding};
use alignist::so3::metrics::{ImageMetrics, first_mode, image_metrics, ll_ceiling, summarize};
use alignist::so3::{
    GridLevel, SymmetryGroup, cube_vertices, equivalents, geodesic_angle, haar_rotation,
    haar_rotations, icosahedron_vertices, maps_set_to_itself, rot_z, tetrahedron_vertices,
    to_row_major_f32,
};
use nalgebra::{Rotation3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn contains(set: &[Rotation3<f64>], r: &Rotation3<f64>) -> bool {
    set.iter().any(|s| geodesic_angle(s, r) < 1e-6)
}

#[test]
fn groups_have_their_orders_and_are_closed() {
    let cases = [
        (SymmetryGroup::Trivial, 1),
        (SymmetryGroup::Tetrahedral, 12),
        (SymmetryGroup::Octahedral, 24),
        (SymmetryGroup::Icosahedral, 60),
        (SymmetryGroup::Cyclic(6), 6),
        (SymmetryGroup::Dihedral(4), 8),
        (SymmetryGroup::Cone, 360),
        (SymmetryGroup::Cylinder, 720),
    ];
    for (group, order) in cases {
        let rots = group.rotations();
        assert_eq!(rots.len(), order, "{group}");
        assert_eq!(group.order(), order, "{group}");
        assert!(
            geodesic_angle(&rots[0], &Rotation3::identity()) < 1e-12,
            "{group}"
        );
        // Distinct elements.
        for (i, a) in rots.iter().enumerate() {
            for b in &rots[..i] {
                assert!(geodesic_angle(a, b) > 1e-6, "{group} has duplicates");
            }
        }
        // Closure (the sampled continuous sets are closed too: 1° steps compose to 1° steps).
        if order <= 60 {
            for a in &rots {
                assert!(contains(&rots, &a.inverse()), "{group}: inverse");
                for b in &rots {
                    assert!(contains(&rots, &(a * b)), "{group}: a·b");
                }
            }
        } else {
            for a in rots.iter().step_by(37) {
                for b in rots.iter().step_by(11) {
                    assert!(contains(&rots, &(a * b)), "{group}: a·b");
                }
            }
        }
    }
}

#[test]
fn groups_fix_their_shapes() {
    let cube = cube_vertices();
    let tet = tetrahedron_vertices();
    let ico = icosahedron_vertices();
    for s in SymmetryGroup::Octahedral.rotations() {
        assert!(maps_set_to_itself(&s, &cube));
    }
    for s in SymmetryGroup::Tetrahedral.rotations() {
        assert!(maps_set_to_itself(&s, &tet));
    }
    for s in SymmetryGroup::Icosahedral.rotations() {
        assert!(maps_set_to_itself(&s, &ico));
    }
    // The shapes are not fixed by more than their group: O does not fix the tetrahedron.
    let moved = SymmetryGroup::Octahedral
        .rotations()
        .iter()
        .filter(|s| !maps_set_to_itself(s, &tet))
        .count();
    assert_eq!(moved, 12);
    // Cone: a ring of points at the apex height stays a ring; the apex stays; the flip moves it.
    let ring: Vec<Vector3<f64>> = (0..360)
        .map(|k| {
            let a = (k as f64).to_radians();
            Vector3::new(a.cos(), a.sin(), -0.5)
        })
        .collect();
    let apex = Vector3::new(0.0, 0.0, 1.0);
    for s in SymmetryGroup::Cone.rotations().iter().step_by(7) {
        assert!(maps_set_to_itself(s, &ring));
        assert!((s * apex - apex).norm() < 1e-12);
    }
    // Cylinder: both end rings swap under the flip.
    let mut rings = ring.clone();
    rings.extend(ring.iter().map(|p| Vector3::new(p.x, p.y, 0.5)));
    for s in SymmetryGroup::Cylinder.rotations().iter().step_by(13) {
        assert!(maps_set_to_itself(s, &rings));
    }
}

#[test]
fn group_names_round_trip_and_bad_names_are_refused() {
    for name in ["none", "T", "O", "I", "C4", "D2", "cone", "cylinder"] {
        let g: SymmetryGroup = name.parse().unwrap();
        assert_eq!(g.to_string(), name);
        let json = serde_json::to_string(&g).unwrap();
        assert_eq!(serde_json::from_str::<SymmetryGroup>(&json).unwrap(), g);
    }
    for bad in ["", "X", "C0", "Cx", "D-1", "cones"] {
        let err = bad.parse::<SymmetryGroup>().unwrap_err().to_string();
        assert!(err.contains("unknown symmetry group"), "{err}");
    }
}

#[test]
fn equivalents_are_gt_times_each_symmetry() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let gt = haar_rotation(&mut rng);
    let group = SymmetryGroup::Octahedral.rotations();
    let eq = equivalents(&gt, &group);
    assert_eq!(eq.len(), 24);
    // The cube's vertices seen in the camera are the same set for every equivalent.
    let seen: Vec<Vector3<f64>> = cube_vertices().iter().map(|v| gt * v).collect();
    for e in &eq {
        let other: Vec<Vector3<f64>> = cube_vertices().iter().map(|v| e * v).collect();
        assert!(
            other
                .iter()
                .all(|p| seen.iter().any(|q| (p - q).norm() < 1e-9))
        );
    }
}

#[test]
fn uniform_distribution_scores_zero_and_point_mass_scores_log_n() {
    let g = GridLevel::new(3).unwrap();
    let centres = g.quaternions();
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    for gt in haar_rotations(&mut rng, 5) {
        let uniform = vec![0.25f32; g.len()];
        let m = image_metrics(&g, &centres, &uniform, &[gt]).unwrap();
        assert!(m.log_likelihood.abs() < 1e-6, "{}", m.log_likelihood);

        let cell = g.cell_of(&gt);
        let mut point = vec![-1000f32; g.len()];
        point[cell as usize] = 0.0;
        let m = image_metrics(&g, &centres, &point, &[gt]).unwrap();
        assert!((m.log_likelihood - (g.len() as f64).ln()).abs() < 1e-9);
        let to_centre = geodesic_angle(&gt, &g.rotation(cell)).to_degrees();
        assert!(
            (m.spread_deg - to_centre).abs() < 1e-4,
            "{} vs {to_centre}",
            m.spread_deg
        );
        assert!((m.argmax_error_deg - to_centre).abs() < 1e-4);
        // The argmax's rotation is the cell's centre (a quaternion, either sign).
        let centre = alignist::so3::to_quaternion(&g.rotation(cell));
        let dot = alignist::so3::quaternion_dot(&m.argmax, &centre);
        assert!(
            (dot.abs() - 1.0).abs() < 1e-9,
            "{:?} vs {centre:?}",
            m.argmax
        );

        // Mass moved 90° away: the spread and the error become ~90°, LL drops far below 0.
        let far = g.cell_of(&(gt * alignist::so3::rot_x(std::f64::consts::FRAC_PI_2)));
        let mut wrong = vec![-1000f32; g.len()];
        wrong[far as usize] = 0.0;
        let m = image_metrics(&g, &centres, &wrong, &[gt]).unwrap();
        assert!((m.spread_deg - 90.0).abs() < 10.0, "{}", m.spread_deg);
        assert!(m.log_likelihood < -100.0);
    }
}

#[test]
fn ll_averages_over_every_equivalent() {
    let g = GridLevel::new(2).unwrap();
    let centres = g.quaternions();
    let gt = haar_rotation(&mut ChaCha8Rng::seed_from_u64(9));
    let eq = equivalents(&gt, &SymmetryGroup::Tetrahedral.rotations());
    // All mass on the first equivalent's cell: 1 of 12 equivalents scores log N, the rest ≈ −∞
    // (the other cells hold e^-50 each), so the mean is far below the one found.
    let mut one = vec![-50f32; g.len()];
    one[g.cell_of(&eq[0]) as usize] = 0.0;
    let m_one = image_metrics(&g, &centres, &one, &eq).unwrap();
    // Mass evenly on all 12 cells: LL = log(N/12), the ceiling.
    let mut all = vec![-50f32; g.len()];
    for e in &eq {
        all[g.cell_of(e) as usize] = 0.0;
    }
    let m_all = image_metrics(&g, &centres, &all, &eq).unwrap();
    let ceiling = ll_ceiling(&g, &eq);
    assert!((ceiling - (g.len() as f64 / 12.0).ln()).abs() < 1e-9);
    assert!((m_all.log_likelihood - ceiling).abs() < 1e-6);
    assert!(m_one.log_likelihood < m_all.log_likelihood - 10.0);
    // Spread is against the nearest equivalent: never more than the way to the own cell centre.
    let to_centre =
        |e: &nalgebra::Rotation3<f64>| geodesic_angle(e, &g.rotation(g.cell_of(e))).to_degrees();
    assert!(m_one.spread_deg <= to_centre(&eq[0]) + 1e-6);
    let mean_to_centre = eq.iter().map(to_centre).sum::<f64>() / 12.0;
    assert!(m_all.spread_deg <= mean_to_centre + 1e-6);
}

#[test]
fn ll_ceilings_match_the_design_notes_at_level_4() {
    // docs/DESIGN.md §2: tet 10.11, cube 9.42, icosa 8.50, cone 8.04, cylinder 7.34 at level 4.
    let g = GridLevel::new(4).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let cases = [
        (SymmetryGroup::Tetrahedral, 10.11),
        (SymmetryGroup::Octahedral, 9.42),
        (SymmetryGroup::Icosahedral, 8.50),
        (SymmetryGroup::Cone, 8.04),
        (SymmetryGroup::Cylinder, 7.34),
    ];
    for (group, expected) in cases {
        let gt = haar_rotation(&mut rng);
        let c = ll_ceiling(&g, &equivalents(&gt, &group.rotations()));
        assert!((c - expected).abs() < 0.02, "{group}: {c} vs {expected}");
    }
}

#[test]
fn metrics_refuse_bad_distributions() {
    let g = GridLevel::new(0).unwrap();
    let centres = g.quaternions();
    let gt = [Rotation3::identity()];
    assert!(image_metrics(&g, &centres, &[0.0; 10], &gt).is_err());
    let mut nan = vec![0f32; g.len()];
    nan[3] = f32::NAN;
    assert!(image_metrics(&g, &centres, &nan, &gt).is_err());
    assert!(image_metrics(&g, &centres, &vec![f32::NEG_INFINITY; g.len()], &gt).is_err());
    assert!(image_metrics(&g, &centres, &vec![0.0; g.len()], &[]).is_err());
}

#[test]
fn summary_gives_accuracy_and_median() {
    let per = [5.0, 40.0, 10.0, 100.0].map(|e| ImageMetrics {
        log_likelihood: 1.0,
        spread_deg: e,
        argmax_error_deg: e,
        mode_error_deg: 2.0 * e,
        argmax: [1.0, 0.0, 0.0, 0.0],
    });
    let s = summarize(&per, &[30.0, 15.0]);
    assert_eq!(s.images, 4);
    assert_eq!(s.accuracy_at, vec![(30.0, 0.5), (15.0, 0.5)]);
    assert!((s.median_error_deg - 25.0).abs() < 1e-12);
    assert!((s.spread_deg - 38.75).abs() < 1e-12);
    assert_eq!(s.half_turn_wrong, 0.0);
    // The first mode's errors, 10, 80, 20, 200: its own AR and median.
    assert_eq!(s.mode_accuracy_at, vec![(30.0, 0.5), (15.0, 0.25)]);
    assert!((s.mode_median_error_deg - 50.0).abs() < 1e-12);
}

/// A point estimate's errors alone (the served answers' summary): the share below each `θ` (strictly)
/// and the median, which for no errors is NaN with no share counted.
#[test]
fn point_errors_give_accuracy_and_median() {
    use alignist::so3::metrics::accuracy_and_median;
    let (acc, median) = accuracy_and_median(&[50.0, 30.0, 3.0], &[30.0, 60.0]);
    assert_eq!(acc, vec![(30.0, 1.0 / 3.0), (60.0, 1.0)]);
    assert_eq!(median, 30.0);
    let (acc, median) = accuracy_and_median(&[], &[30.0]);
    assert_eq!(acc, vec![(30.0, 0.0)]);
    assert!(median.is_nan());
}

/// A mode of several cells outweighs one sharper cell 90° away: the argmax answers the sharp
/// cell, the first mode the massive one; raise the single cell above the group's mass and the
/// two agree on it.
#[test]
fn the_first_mode_weighs_mass_where_the_argmax_takes_the_sharpest_cell() {
    // Level 3: neighbouring cells about 7.5° apart, so a 15° group holds several.
    let g = GridLevel::new(3).unwrap();
    let centres = g.quaternions();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    for r in haar_rotations(&mut rng, 4) {
        let b = g.rotation(g.cell_of(&r));
        let a = g.rotation(g.cell_of(&(b * alignist::so3::rot_x(std::f64::consts::FRAC_PI_2))));
        let group: Vec<usize> = (0..g.len())
            .filter(|&i| geodesic_angle(&g.rotation(i as u64), &b).to_degrees() < 14.0)
            .collect();
        assert!(group.len() >= 2, "{} cells within 14°", group.len());
        let spread = |single: f32| {
            // b's cell a little above the rest of its group: the group's seed (within 15°).
            let mut w = vec![-10f32; g.len()];
            group.iter().for_each(|&i| w[i] = 4.0);
            w[g.cell_of(&b) as usize] = 4.05;
            w[g.cell_of(&a) as usize] = 4.0 + (group.len() as f32).ln() + single;
            w
        };
        let m = image_metrics(&g, &centres, &spread(-0.3), &[b]).unwrap();
        assert!(m.argmax_error_deg > 80.0, "argmax {}", m.argmax_error_deg);
        assert!(m.mode_error_deg < 5.0, "first mode {}", m.mode_error_deg);
        let m = image_metrics(&g, &centres, &spread(0.3), &[a]).unwrap();
        assert!(
            m.argmax_error_deg < 1e-6 && m.mode_error_deg < 1e-6,
            "{m:?}"
        );
    }
}

/// Every distribution has a first mode, even one whose masses all underflowed to zero; no cells,
/// none.
#[test]
fn a_first_mode_exists_for_any_cells() {
    let g = GridLevel::new(1).unwrap();
    let zero = first_mode(&g, &vec![0.0; g.len()]).expect("a mode of zero mass");
    assert_eq!((zero.cells, zero.probability), (1, 0.0));
    assert!(zero.quaternion.iter().all(|v| v.is_finite()), "{zero:?}");
    assert!(first_mode(&g, &[]).is_none());
}

#[test]
fn summary_counts_the_half_turn_twins() {
    // 150° and beyond is a twin; 149.9° is not.
    let per = [5.0, 149.9, 150.0, 179.0, 30.0].map(|e| ImageMetrics {
        log_likelihood: if e > 100.0 { -1.0 } else { 1.0 },
        spread_deg: e,
        argmax_error_deg: e,
        mode_error_deg: 2.0 * e,
        argmax: [1.0, 0.0, 0.0, 0.0],
    });
    let s = summarize(&per, &[30.0]);
    assert!((s.half_turn_wrong - 0.4).abs() < 1e-12);
    assert!((s.confidently_wrong - 0.6).abs() < 1e-12);
}

#[test]
fn cube_encoding_separates_every_cell_of_level_2() {
    let g = GridLevel::new(2).unwrap();
    let mats = g.matrices_f32();
    let enc = cube_encoding(&mats);
    assert_eq!(enc.len(), mats.len() * CUBE_ENCODING_DIM);
    let rows: Vec<&[f32]> = enc.chunks(CUBE_ENCODING_DIM).collect();
    let mut min_d2 = f32::INFINITY;
    for i in 0..rows.len() {
        for j in 0..i {
            let d2: f32 = rows[i]
                .iter()
                .zip(rows[j])
                .map(|(a, b)| (a - b) * (a - b))
                .sum();
            min_d2 = min_d2.min(d2);
        }
    }
    assert!(
        min_d2 > 1e-3,
        "closest pair of encodings at squared distance {min_d2}"
    );
}

#[test]
fn cube_encoding_matches_its_definition() {
    let r = rot_z(0.7) * alignist::so3::rot_x(-1.2);
    let enc = cube_encoding(&[to_row_major_f32(&r)]);
    // Vertex 7 is (1, 1, 1); its rotated y coordinate is row 1 of R times (1, 1, 1).
    let v = r * Vector3::new(1.0, 1.0, 1.0);
    let y = v.y as f32;
    // sin at frequency 1 sits at 7·3 + 1; cos at frequency 4 at 4·24 + 24 + 22.
    assert!((enc[22] - y.sin()).abs() < 1e-6);
    assert!((enc[4 * 24 + 24 + 22] - (4.0 * y).cos()).abs() < 1e-5);
    // The tensor path equals the rows.
    let device = alignist::backend::device();
    let t = RotationEncoding::Cube.encode_tensor(&[to_row_major_f32(&r)], &device);
    assert_eq!(t.dims(), [1, 144]);
    let data: Vec<f32> = t.into_data().try_to_vec::<f32>().unwrap();
    assert_eq!(data, enc);
}

#[test]
fn ipdf_encoding_matches_hand_computed_values() {
    // Identity, 2 frequencies: entries (1,0,0, 0,1,0, 0,0,1).
    let id = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0f32];
    let e = ipdf_encoding(&[id], 2);
    assert_eq!(e.len(), 36);
    let s1 = 1f32.sin();
    let s2 = 2f32.sin();
    let c2 = 2f32.cos();
    let expect = [
        s1,
        0.0,
        0.0,
        0.0,
        s1,
        0.0,
        0.0,
        0.0,
        s1, // sin(1·r)
        1f32.cos(),
        1.0,
        1.0,
        1.0,
        1f32.cos(),
        1.0,
        1.0,
        1.0,
        1f32.cos(), // cos(1·r)
        s2,
        0.0,
        0.0,
        0.0,
        s2,
        0.0,
        0.0,
        0.0,
        s2, // sin(2·r)
        c2,
        1.0,
        1.0,
        1.0,
        c2,
        1.0,
        1.0,
        1.0,
        c2, // cos(2·r)
    ];
    for (a, b) in e.iter().zip(expect) {
        assert!((a - b).abs() < 1e-7);
    }
    // 90° about z: entries (0,−1,0, 1,0,0, 0,0,1); sin(−1) at index 1, cos(−1) at 10.
    let rz = [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0f32];
    let e = ipdf_encoding(&[id, rz], 1);
    assert_eq!(e.len(), 36);
    assert!((e[18 + 1] - (-1f32).sin()).abs() < 1e-7);
    assert!((e[18 + 3] - s1).abs() < 1e-7);
    assert!((e[18 + 9 + 1] - (-1f32).cos()).abs() < 1e-7);
    assert_eq!(RotationEncoding::Ipdf { frequencies: 3 }.dim(), 54);
}

#[test]
fn recorded_symmetry_sets_are_named_by_their_group() {
    use alignist::so3::{SymmetryGroup, rot_x};
    for name in ["none", "T", "O", "I", "C6", "D4", "cone", "cylinder"] {
        let g: SymmetryGroup = name.parse().unwrap();
        let mut rotations = g.rotations();
        rotations.reverse();
        assert_eq!(SymmetryGroup::identify(&rotations), Some(g), "{name}");
    }
    assert_eq!(SymmetryGroup::Cylinder.axis(), Some(nalgebra::Vector3::z()));
    assert!(SymmetryGroup::Cone.is_continuous() && !SymmetryGroup::Octahedral.is_continuous());
    assert_eq!(SymmetryGroup::Octahedral.axis(), None);
    // A set that is no named group (C4 turned about x) is not given a name.
    let turned: Vec<_> = SymmetryGroup::Cyclic(4)
        .rotations()
        .iter()
        .map(|s| rot_x(0.3) * s * rot_x(-0.3))
        .collect();
    assert_eq!(SymmetryGroup::identify(&turned), None);
}
