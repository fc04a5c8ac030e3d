//! The object's symmetry, discovered from its SDF expert rather than declared (docs/DESIGN.md §2,
//! "Symmetry discovered").
//!
//! A rotation `S` is a symmetry of the part when the surface moved by `S` lies on the surface:
//! the SDF is zero at `S·p` for every surface point `p`. Its *residual* is the mean `|SDF(S·p)|`
//! over surface points (NOCS units, radius 1), beside the residual of the identity, which is the
//! expert's own error on the surface. Candidates (every cell of a grid level, and the cells of the
//! experts' mode table where there is one) are scored, thinned to the best within
//! [`DiscoveryConfig::spacing_deg`], refined by a pattern search, and accepted when their residual
//! is within [`DiscoveryConfig::tolerance`] of the identity's (near-symmetries within
//! [`DiscoveryConfig::near_tolerance`]). The accepted rotations are then named: their axes and the
//! orders about each give `none`, `C<n>`, `D<n>`, `cone`, `cylinder`, `T`, `O`, `I` or `sphere`.

use std::f64::consts::PI;

use nalgebra::{Rotation3, Unit, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::cad::Mesh;
use crate::so3::{GridLevel, So3Error, geodesic_angle};

/// Orders above this about one axis are reported as a continuous symmetry (`cone`, `cylinder`).
pub const MAX_FINITE_ORDER: usize = 12;

/// How symmetries are searched and accepted.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DiscoveryConfig {
    /// Surface points whose distances make a residual.
    pub points: usize,
    /// Grid level whose every cell is a candidate (3: 36 864 cells, within 11.25° of any
    /// rotation).
    pub level: u8,
    /// Candidates closer than this (degrees) to a better one are dropped before refinement.
    pub spacing_deg: f64,
    /// At most this many candidates are refined.
    pub max_refined: usize,
    /// A symmetry's residual may exceed the identity's by this much (NOCS units): 0.012, 1.2 %
    /// of the part's radius, the roundness of a scanned cup (YCB's scans: cups and cans come out
    /// continuous at 0.012 and not at 0.006, and no asymmetric part gains a symmetry).
    pub tolerance: f64,
    /// A near-symmetry's by this much (a symmetry broken by a small feature: a hole, a logo).
    pub near_tolerance: f64,
    /// Seed of the surface points.
    pub seed: u64,
}

impl Default for DiscoveryConfig {
    fn default() -> Self {
        DiscoveryConfig {
            points: 384,
            level: 3,
            spacing_deg: 12.0,
            max_refined: 400,
            tolerance: 0.012,
            near_tolerance: 0.04,
            seed: 0,
        }
    }
}

/// What the experts say about an object's symmetry, as the manifests record it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiscoveredSymmetry {
    /// `none`, `C<n>`, `D<n>`, `cone`, `cylinder`, `T`, `O`, `I` or `sphere` (in the grammar of
    /// [`crate::so3::SymmetryGroup`], plus `sphere`).
    pub label: String,
    /// The principal axis (`C<n>`, `D<n>`, `cone`, `cylinder`) or the axes of highest order
    /// (`T`, `O`, `I`), unit vectors in the mesh's frame; empty for `none`.
    pub axes: Vec<[f64; 3]>,
    /// How clearly the accepted symmetries stand apart from the rejected candidates, in [0, 1]:
    /// `min(1 − worst accepted / tolerance, 1 − tolerance / best rejected)` on residuals above
    /// the identity's. Near-symmetries lower it.
    pub confidence: f64,
    /// Distinct symmetries found (identity included; a continuous one counts its samples).
    pub rotations: usize,
    /// The identity's residual: the expert's own error on the surface (NOCS units).
    pub baseline: f64,
    /// A larger group that holds up to [`DiscoveryConfig::near_tolerance`]: the part is nearly
    /// symmetric (a symmetry broken by a small feature).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub near: Option<NearSymmetry>,
    /// How it was searched.
    pub config: DiscoveryConfig,
    /// The symmetries found, row-major, identity first (a continuous one as its samples every
    /// 10°): the equivalent ground truths of an evaluation when none was declared.
    #[serde(default)]
    pub found: Vec<[f64; 9]>,
}

impl DiscoveredSymmetry {
    /// [`DiscoveredSymmetry::found`] as rotations (entries that are not rotations left out).
    pub fn rotations(&self) -> Vec<Rotation3<f64>> {
        self.found
            .iter()
            .filter_map(|m| crate::so3::from_row_major(*m).ok())
            .collect()
    }
}

/// A near-symmetry of a part.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NearSymmetry {
    /// The group the near-symmetries complete, as [`DiscoveredSymmetry::label`].
    pub label: String,
    /// Its principal axes, as [`DiscoveredSymmetry::axes`].
    pub axes: Vec<[f64; 3]>,
    /// The worst residual among its rotations above the identity's (NOCS units).
    pub residual: f64,
}

impl NearSymmetry {
    /// Rotations that nearly map the part onto itself, known from the label and the principal
    /// axis (the *twins* of a pose, `R_gt·S`, that twin sampling draws around): for `C<n>` and
    /// `D<n>` the `n − 1` turns about the axis, for `cone` and `cylinder` the turns about it
    /// every 10°. A `D<n>`'s or a cylinder's flips, and the groups `T`, `O`, `I`, are not
    /// recorded with their axes, so they give no twins. Some may be exact symmetries (a `C2`
    /// part that is nearly `D2` records the `D2`'s axis): drawing around those draws around a
    /// mode, which the mode table does anyway.
    pub fn twins(&self) -> Vec<Rotation3<f64>> {
        let Some(axis) = self.axes.first().map(|a| Vector3::from(*a)) else {
            return Vec::new();
        };
        let Some(axis) = Unit::try_new(axis, 1e-9) else {
            return Vec::new();
        };
        let label = self.label.as_str();
        let turns = match label {
            "cone" | "cylinder" => 36,
            _ => match label
                .strip_prefix('C')
                .or_else(|| label.strip_prefix('D'))
                .and_then(|n| n.parse::<usize>().ok())
            {
                Some(n) if n >= 2 => n,
                _ => return Vec::new(),
            },
        };
        (1..turns)
            .map(|k| {
                let angle = std::f64::consts::TAU * k as f64 / turns as f64;
                Rotation3::from_axis_angle(&axis, angle)
            })
            .collect()
    }
}

/// Mean `|sdf(Q·p)|` over `points`.
fn residual(
    sdf: &(dyn Fn(&[Vector3<f32>]) -> Vec<f32> + Sync),
    q: &Rotation3<f64>,
    points: &[Vector3<f32>],
) -> f64 {
    let m = q.cast::<f32>();
    let moved: Vec<Vector3<f32>> = points.iter().map(|p| m * p).collect();
    let d = sdf(&moved);
    d.iter().map(|v| f64::from(v.abs())).sum::<f64>() / d.len().max(1) as f64
}

/// A pattern search from `q` on the residual: steps about the three axes, halved from 6° to
/// 0.05° whenever none improves.
fn refine(
    sdf: &(dyn Fn(&[Vector3<f32>]) -> Vec<f32> + Sync),
    q: Rotation3<f64>,
    points: &[Vector3<f32>],
) -> (Rotation3<f64>, f64) {
    let (mut best, mut value) = (q, residual(sdf, &q, points));
    let mut step = 6f64.to_radians();
    while step > 0.05f64.to_radians() {
        let mut moved = false;
        for axis in [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()] {
            for sign in [1.0, -1.0] {
                let trial = Rotation3::from_axis_angle(&axis, sign * step) * best;
                let v = residual(sdf, &trial, points);
                if v < value {
                    (best, value, moved) = (trial, v, true);
                }
            }
        }
        if !moved {
            step /= 2.0;
        }
    }
    (best, value)
}

/// The symmetry of the part `mesh` (in NOCS) as its SDF `sdf` (points → signed distances, e.g.
/// the baked SDF expert) shows it, searched over every cell of `config.level` and `extra`
/// candidates (the mode table's cells).
pub fn discover_symmetry(
    sdf: &(dyn Fn(&[Vector3<f32>]) -> Vec<f32> + Sync),
    mesh: &Mesh,
    extra: &[Rotation3<f64>],
    config: &DiscoveryConfig,
) -> Result<DiscoveredSymmetry, So3Error> {
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed ^ 0x5e7e);
    let points = mesh.sample_surface_points(config.points.max(16), &mut rng);
    let baseline = residual(sdf, &Rotation3::identity(), &points);
    let grid = GridLevel::new(config.level)?;
    let candidates: Vec<Rotation3<f64>> = (0..grid.len() as u64)
        .map(|c| grid.rotation(c))
        .chain(extra.iter().copied())
        .collect();
    let mut scored: Vec<(f64, Rotation3<f64>)> = candidates
        .par_iter()
        .map(|q| (residual(sdf, q, &points), *q))
        .collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    // The best candidate of each neighbourhood, best first.
    let spacing = config.spacing_deg.to_radians();
    let mut seeds: Vec<Rotation3<f64>> = vec![Rotation3::identity()];
    for (_, q) in &scored {
        if seeds.len() >= config.max_refined.max(1) {
            break;
        }
        if seeds.iter().all(|s| geodesic_angle(s, q) > spacing) {
            seeds.push(*q);
        }
    }
    let mut refined: Vec<(f64, Rotation3<f64>)> = seeds
        .par_iter()
        .map(|q| {
            let (r, v) = refine(sdf, *q, &points);
            (v - baseline, r)
        })
        .collect();
    refined[0] = (0.0, Rotation3::identity());
    // Rotations about the axes of the near-symmetries, every 10°: a continuous symmetry is one
    // that holds all round.
    let near: Vec<Rotation3<f64>> = refined
        .iter()
        .filter(|(e, _)| *e <= config.near_tolerance)
        .map(|(_, q)| *q)
        .collect();
    let rings: Vec<Ring> = axis_groups(&near)
        .into_iter()
        .map(|g| {
            let samples: Vec<Rotation3<f64>> = (1..36)
                .map(|k| Rotation3::from_axis_angle(&g.axis, (10 * k) as f64 * PI / 180.0))
                .collect();
            let excess = samples
                .par_iter()
                .map(|q| residual(sdf, q, &points) - baseline)
                .reduce(|| f64::NEG_INFINITY, f64::max);
            Ring {
                axis: g.axis,
                samples,
                excess,
            }
        })
        .collect();
    Ok(name_symmetries(&refined, &rings, baseline, config))
}

/// The rotations about one axis every 10°, and the worst of their residuals above the
/// identity's.
struct Ring {
    axis: Unit<Vector3<f64>>,
    samples: Vec<Rotation3<f64>>,
    excess: f64,
}

/// The symmetry of the part `mesh` (in NOCS, closed) from its exact SDF, baked at 64³ as the
/// SDF expert is: the geometry's own answer, for parts whose experts are not trained yet.
pub fn mesh_symmetry(
    mesh: &Mesh,
    config: &DiscoveryConfig,
) -> Result<DiscoveredSymmetry, super::ExpertError> {
    let exact = crate::cad::SignedDistance::new(mesh)?;
    let bake = super::baked::VoxelGrid::bake(64, 1.05, 1, |p| exact.distances(p));
    Ok(discover_symmetry(&|p| bake.sample(p), mesh, &[], config)?)
}

/// Names the group of the refined candidates `(residual above the identity's, rotation)`.
fn name_symmetries(
    refined: &[(f64, Rotation3<f64>)],
    rings: &[Ring],
    baseline: f64,
    config: &DiscoveryConfig,
) -> DiscoveredSymmetry {
    let on_axis = |q: &Rotation3<f64>, axis: &Unit<Vector3<f64>>| {
        axis_angle(q).is_some_and(|(a, _)| a.dot(axis).abs() > 5f64.to_radians().cos())
    };
    // The rotations within `within`: those about an axis that is continuous within it replaced
    // by its ring, and a few about one axis that form no cyclic group left out (the minima of a
    // nearly flat ring are accidents of the scan, not a finite group).
    let distinct = |within: f64| {
        let mut out: Vec<Rotation3<f64>> = Vec::new();
        let whole: Vec<&Ring> = rings.iter().filter(|r| r.excess <= within).collect();
        let mut candidates: Vec<(f64, Rotation3<f64>)> = refined
            .iter()
            .filter(|(_, q)| !whole.iter().any(|r| on_axis(q, &r.axis)))
            .copied()
            .collect();
        for r in &whole {
            candidates.extend(r.samples.iter().map(|q| (r.excess.max(0.0), *q)));
        }
        candidates.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (e, q) in &candidates {
            if *e <= within && out.iter().all(|s| geodesic_angle(s, q) > 2f64.to_radians()) {
                out.push(*q);
            }
        }
        let incoherent: Vec<Unit<Vector3<f64>>> = axis_groups(&out)
            .into_iter()
            .filter(|g| g.angles.len() < MAX_FINITE_ORDER && g.order() > MAX_FINITE_ORDER)
            .map(|g| g.axis)
            .collect();
        out.retain(|q| !incoherent.iter().any(|a| on_axis(q, a)));
        out
    };
    let spacing = config.spacing_deg.to_radians();
    let accepted = closed_extension(
        &[Rotation3::identity()],
        &distinct(config.tolerance),
        spacing,
    );
    let (label, axes) = name_group(&accepted);
    // Every judgement made, as (residual above the identity's, accepted): the refined candidates
    // off the rings, and each ring as a whole.
    let judged: Vec<(f64, bool)> = refined
        .iter()
        .skip(1)
        .filter(|(_, q)| {
            !rings
                .iter()
                .any(|r| r.excess <= config.tolerance && on_axis(q, &r.axis))
        })
        .map(|(e, _)| *e)
        .chain(rings.iter().map(|r| r.excess))
        .map(|e| (e, e <= config.tolerance))
        .collect();
    let worst = judged
        .iter()
        .filter(|(_, ok)| *ok)
        .map(|(e, _)| e.max(0.0))
        .fold(0.0, f64::max);
    let best_rejected = judged
        .iter()
        .filter(|(_, ok)| !ok)
        .map(|(e, _)| *e)
        .fold(f64::INFINITY, f64::min);
    let confidence = (1.0 - worst / config.tolerance).min(1.0 - config.tolerance / best_rejected);
    let near_set = closed_extension(&accepted, &distinct(config.near_tolerance), spacing);
    let near = (near_set.len() > accepted.len())
        .then(|| {
            let (near_label, near_axes) = name_group(&near_set);
            (near_label != label).then(|| NearSymmetry {
                label: near_label,
                axes: near_axes,
                residual: judged
                    .iter()
                    .filter(|(e, _)| *e <= config.near_tolerance)
                    .map(|(e, _)| *e)
                    .fold(0.0, f64::max),
            })
        })
        .flatten();
    DiscoveredSymmetry {
        label,
        axes,
        confidence: confidence.clamp(0.0, 1.0),
        rotations: accepted.len(),
        baseline,
        near,
        config: *config,
        found: accepted.iter().map(crate::so3::to_row_major).collect(),
    }
}

/// `group` extended by those of `candidates` (best first) that keep it closed: a candidate joins
/// when its products with every member land within `within` (the candidates' spacing) of a
/// member or a candidate, so that a stray rotation that happens to fit loosely does not make up
/// a larger group.
fn closed_extension(
    group: &[Rotation3<f64>],
    candidates: &[Rotation3<f64>],
    within: f64,
) -> Vec<Rotation3<f64>> {
    let near = |r: &Rotation3<f64>, set: &[Rotation3<f64>]| {
        set.iter().any(|s| geodesic_angle(s, r) < within)
    };
    let mut out = group.to_vec();
    for c in candidates {
        if near(c, &out) {
            continue;
        }
        // Its products with every member and with itself (a lone 45° turn is no C8 without 90°).
        let closes = out
            .iter()
            .chain(std::iter::once(c))
            .all(|s| near(&(c * s), candidates) && near(&(s * c), candidates));
        if closes {
            out.push(*c);
        }
    }
    out
}

/// One rotation axis of a set of symmetries and the angles about it (radians in `(0, 2π)`).
struct AxisGroup {
    axis: Unit<Vector3<f64>>,
    angles: Vec<f64>,
}

impl AxisGroup {
    /// The order of the rotations about this axis: from the count of distinct angles and from
    /// the smallest angle, whichever is larger (a missed rotation does not lower it).
    fn order(&self) -> usize {
        let count = self.angles.len() + 1;
        let multiples_of = |n: usize| {
            let step = 2.0 * PI / n as f64;
            self.angles.iter().all(|a| {
                let off = (a / step - (a / step).round()).abs() * step;
                off < 4f64.to_radians()
            })
        };
        if count > MAX_FINITE_ORDER {
            return count;
        }
        // The smallest cyclic group that holds every angle found (a missed rotation does not
        // lower the order); none up to the limit: continuous.
        (count..=MAX_FINITE_ORDER)
            .find(|&n| multiples_of(n))
            .unwrap_or(MAX_FINITE_ORDER + 1)
    }

    fn is_flip(&self) -> bool {
        self.angles
            .iter()
            .any(|a| (a - PI).abs() < 5f64.to_radians())
    }
}

/// The axis and angle (in `[0, π]`) of `r` through its quaternion, which stays exact at 180°
/// (where the matrix's skew part, and with it nalgebra's `axis_angle`, vanishes); `None` for the
/// identity.
fn axis_angle(r: &Rotation3<f64>) -> Option<(Unit<Vector3<f64>>, f64)> {
    let q = nalgebra::UnitQuaternion::from_rotation_matrix(r);
    let (w, v) = (q.w, q.imag());
    let v = if w < 0.0 { -v } else { v };
    let angle = 2.0 * v.norm().atan2(w.abs());
    Unit::try_new(v, 1e-12).map(|axis| (axis, angle))
}

/// The rotations' axes with the angles about each (axes within 5° are one).
fn axis_groups(rotations: &[Rotation3<f64>]) -> Vec<AxisGroup> {
    let mut groups: Vec<AxisGroup> = Vec::new();
    for r in rotations {
        let Some((axis, angle)) = axis_angle(r) else {
            continue;
        };
        if angle < 1f64.to_radians() {
            continue;
        }
        match groups
            .iter_mut()
            .find(|g| g.axis.dot(&axis).abs() > 5f64.to_radians().cos())
        {
            Some(g) => {
                let a = if g.axis.dot(&axis) > 0.0 {
                    angle
                } else {
                    2.0 * PI - angle
                };
                if g.angles.iter().all(|b| (a - b).abs() > 2f64.to_radians()) {
                    g.angles.push(a);
                }
            }
            None => groups.push(AxisGroup {
                axis,
                angles: vec![angle],
            }),
        }
    }
    groups
}

/// The name and principal axes of the group of `rotations` (identity included).
fn name_group(rotations: &[Rotation3<f64>]) -> (String, Vec<[f64; 3]>) {
    let groups = axis_groups(rotations);
    let unit = |a: &Unit<Vector3<f64>>| -> [f64; 3] {
        // The sign that makes the largest component positive, for stable reports.
        let v = a.into_inner();
        let i = v.iamax();
        let v = if v[i] < 0.0 { -v } else { v };
        [v.x, v.y, v.z]
    };
    let continuous: Vec<&AxisGroup> = groups
        .iter()
        .filter(|g| g.order() > MAX_FINITE_ORDER)
        .collect();
    let perpendicular_flips = |axis: &Unit<Vector3<f64>>| {
        groups
            .iter()
            .filter(|g| g.is_flip() && g.axis.dot(axis).abs() < 10f64.to_radians().sin())
            .count()
    };
    match continuous.as_slice() {
        [] => {}
        [one] => {
            let label = if perpendicular_flips(&one.axis) > 0 {
                "cylinder"
            } else {
                "cone"
            };
            return (label.into(), vec![unit(&one.axis)]);
        }
        _ => return ("sphere".into(), Vec::new()),
    }
    let of_order =
        |n: usize| -> Vec<&AxisGroup> { groups.iter().filter(|g| g.order() == n).collect() };
    for (n, label) in [(5, "I"), (4, "O"), (3, "T")] {
        let axes = of_order(n);
        if axes.len() >= 2 {
            return (label.into(), axes.iter().map(|g| unit(&g.axis)).collect());
        }
    }
    let Some(principal) = groups.iter().max_by_key(|g| g.order()) else {
        return ("none".into(), Vec::new());
    };
    let n = principal.order();
    let label = if perpendicular_flips(&principal.axis) > 0 {
        format!("D{n}")
    } else {
        format!("C{n}")
    };
    (label, vec![unit(&principal.axis)])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::so3::{SymmetryGroup, rot_x};

    #[test]
    fn the_groups_of_declared_symmetries_are_named_back() {
        for (group, label) in [
            (SymmetryGroup::Trivial, "none"),
            (SymmetryGroup::Cyclic(2), "C2"),
            (SymmetryGroup::Cyclic(5), "C5"),
            (SymmetryGroup::Dihedral(2), "D2"),
            (SymmetryGroup::Dihedral(6), "D6"),
            (SymmetryGroup::Tetrahedral, "T"),
            (SymmetryGroup::Octahedral, "O"),
            (SymmetryGroup::Icosahedral, "I"),
            (SymmetryGroup::Cone, "cone"),
            (SymmetryGroup::Cylinder, "cylinder"),
        ] {
            // Continuous groups thinned to every 12°, as the discovery's spacing leaves them.
            let rotations: Vec<_> = group
                .rotations()
                .into_iter()
                .enumerate()
                .filter(|(i, _)| !group.is_continuous() || i % 12 == 0)
                .map(|(_, r)| r)
                .collect();
            assert_eq!(name_group(&rotations).0, label, "{group}");
            // Turned as a whole: the name does not depend on the frame.
            let turn = rot_x(0.4) * Rotation3::from_axis_angle(&Vector3::y_axis(), 1.1);
            let turned: Vec<_> = rotations
                .iter()
                .map(|r| turn * r * turn.inverse())
                .collect();
            assert_eq!(name_group(&turned).0, label, "{group} turned");
        }
    }

    #[test]
    fn a_cyclic_axis_is_reported_in_the_mesh_frame() {
        let axis = Unit::new_normalize(Vector3::new(0.0, 1.0, 1.0));
        let rotations: Vec<_> = (0..4)
            .map(|k| Rotation3::from_axis_angle(&axis, k as f64 * PI / 2.0))
            .collect();
        let (label, axes) = name_group(&rotations);
        assert_eq!(label, "C4");
        let a = Vector3::from(axes[0]);
        assert!((a.dot(&axis) - 1.0).abs() < 1e-9, "{a:?}");
    }
}
