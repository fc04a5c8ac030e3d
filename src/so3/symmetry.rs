//! Symmetry groups of objects, as lists of rotations (SYMSOL conventions, docs/DESIGN.md §1).
//!
//! A rotation `S` is a symmetry when `S·X = X` for the object's surface `X` (in canonical
//! coordinates); then `R_gt·S` shows the same image as `R_gt`, so [`equivalents`] lists every
//! equivalent ground truth of an image.

use std::fmt;
use std::str::FromStr;

use nalgebra::{Matrix3, Rotation3, Unit, Vector3};
use serde::{Deserialize, Serialize};

use super::{So3Error, geodesic_angle, rot_x, rot_z};

/// The golden ratio φ, used by the icosahedron's canonical vertices `(0, ±1, ±φ)` (cyclic).
pub const GOLDEN_RATIO: f64 = 1.618_033_988_749_895;

/// Number of rotations that sample the continuous symmetry about z (SYMSOL: every 1°).
pub const CONTINUOUS_STEPS: usize = 360;

/// A symmetry group of an object, named as in the model manifest and on the CLI
/// (`none`, `T`, `O`, `I`, `C<n>`, `D<n>`, `cone`, `cylinder`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum SymmetryGroup {
    /// Only the identity.
    Trivial,
    /// The tetrahedral group T (12), for the vertices `(1,1,1), (1,−1,−1), (−1,1,−1), (−1,−1,1)`.
    Tetrahedral,
    /// The octahedral group O (24): the signed permutation matrices of determinant 1.
    Octahedral,
    /// The icosahedral group I (60), for the vertices that are cyclic permutations of `(0, ±1, ±φ)`.
    Icosahedral,
    /// `Cn`: `n` rotations about z.
    Cyclic(u32),
    /// `Dn`: `Cn` and `Cn` composed with the flip about x (`2n`).
    Dihedral(u32),
    /// The cone's continuous symmetry about z, sampled at 1° (360).
    Cone,
    /// The cylinder's: the cone's set times the flip about x (720).
    Cylinder,
}

impl SymmetryGroup {
    /// The rotations of the group (identity first).
    pub fn rotations(&self) -> Vec<Rotation3<f64>> {
        match *self {
            SymmetryGroup::Trivial => vec![Rotation3::identity()],
            SymmetryGroup::Octahedral => octahedral(),
            SymmetryGroup::Tetrahedral => {
                let verts = tetrahedron_vertices();
                octahedral()
                    .into_iter()
                    .filter(|s| maps_set_to_itself(s, &verts))
                    .collect()
            }
            SymmetryGroup::Icosahedral => icosahedral(),
            SymmetryGroup::Cyclic(n) => cyclic(n as usize),
            SymmetryGroup::Dihedral(n) => with_flip(cyclic(n as usize)),
            SymmetryGroup::Cone => cyclic(CONTINUOUS_STEPS),
            SymmetryGroup::Cylinder => with_flip(cyclic(CONTINUOUS_STEPS)),
        }
    }

    /// The group whose [`SymmetryGroup::rotations`] are `rotations` (as a set, to 1e-6 rad), if
    /// one is: how a recorded list of rotations is named for clients. `None` for any other set.
    pub fn identify(rotations: &[Rotation3<f64>]) -> Option<SymmetryGroup> {
        let n = rotations.len();
        let mut candidates = vec![
            SymmetryGroup::Trivial,
            SymmetryGroup::Tetrahedral,
            SymmetryGroup::Octahedral,
            SymmetryGroup::Icosahedral,
            SymmetryGroup::Cone,
            SymmetryGroup::Cylinder,
        ];
        if let Ok(k) = u32::try_from(n) {
            candidates.push(SymmetryGroup::Cyclic(k));
            if n.is_multiple_of(2) {
                candidates.push(SymmetryGroup::Dihedral(k / 2));
            }
        }
        candidates.into_iter().find(|g| {
            g.order() == n
                && g.rotations()
                    .iter()
                    .all(|s| rotations.iter().any(|r| geodesic_angle(r, s) < 1e-6))
        })
    }

    /// The axis of the group's rotations about one axis (`Cn`, `Dn`, cone, cylinder: z), `None`
    /// for the others.
    pub fn axis(&self) -> Option<Vector3<f64>> {
        match self {
            SymmetryGroup::Cyclic(n) if *n > 1 => Some(Vector3::z()),
            SymmetryGroup::Dihedral(_) | SymmetryGroup::Cone | SymmetryGroup::Cylinder => {
                Some(Vector3::z())
            }
            _ => None,
        }
    }

    /// Whether the group stands for a continuous symmetry (sampled at 1°).
    pub fn is_continuous(&self) -> bool {
        matches!(self, SymmetryGroup::Cone | SymmetryGroup::Cylinder)
    }

    /// Number of rotations in [`SymmetryGroup::rotations`].
    pub fn order(&self) -> usize {
        match *self {
            SymmetryGroup::Trivial => 1,
            SymmetryGroup::Tetrahedral => 12,
            SymmetryGroup::Octahedral => 24,
            SymmetryGroup::Icosahedral => 60,
            SymmetryGroup::Cyclic(n) => n as usize,
            SymmetryGroup::Dihedral(n) => 2 * n as usize,
            SymmetryGroup::Cone => CONTINUOUS_STEPS,
            SymmetryGroup::Cylinder => 2 * CONTINUOUS_STEPS,
        }
    }
}

/// Every equivalent ground truth of an image whose ground truth is `r_gt`: `R_gt·S` for each `S`
/// of `group`.
pub fn equivalents(r_gt: &Rotation3<f64>, group: &[Rotation3<f64>]) -> Vec<Rotation3<f64>> {
    group.iter().map(|s| r_gt * s).collect()
}

impl fmt::Display for SymmetryGroup {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SymmetryGroup::Trivial => write!(f, "none"),
            SymmetryGroup::Tetrahedral => write!(f, "T"),
            SymmetryGroup::Octahedral => write!(f, "O"),
            SymmetryGroup::Icosahedral => write!(f, "I"),
            SymmetryGroup::Cyclic(n) => write!(f, "C{n}"),
            SymmetryGroup::Dihedral(n) => write!(f, "D{n}"),
            SymmetryGroup::Cone => write!(f, "cone"),
            SymmetryGroup::Cylinder => write!(f, "cylinder"),
        }
    }
}

impl FromStr for SymmetryGroup {
    type Err = So3Error;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || So3Error::UnknownGroup(s.to_string());
        let parse_n = |rest: &str| -> Result<u32, So3Error> {
            match rest.parse::<u32>() {
                Ok(n) if (1..=3600).contains(&n) => Ok(n),
                _ => Err(bad()),
            }
        };
        match s {
            "none" | "C1" => Ok(SymmetryGroup::Trivial),
            "T" => Ok(SymmetryGroup::Tetrahedral),
            "O" => Ok(SymmetryGroup::Octahedral),
            "I" => Ok(SymmetryGroup::Icosahedral),
            "cone" => Ok(SymmetryGroup::Cone),
            "cylinder" => Ok(SymmetryGroup::Cylinder),
            _ if s.starts_with('C') => parse_n(&s[1..]).map(SymmetryGroup::Cyclic),
            _ if s.starts_with('D') => parse_n(&s[1..]).map(SymmetryGroup::Dihedral),
            _ => Err(bad()),
        }
    }
}

impl TryFrom<String> for SymmetryGroup {
    type Error = So3Error;
    fn try_from(s: String) -> Result<Self, Self::Error> {
        s.parse()
    }
}

impl From<SymmetryGroup> for String {
    fn from(g: SymmetryGroup) -> String {
        g.to_string()
    }
}

/// The canonical tetrahedron's vertices (docs/DESIGN.md §1).
pub fn tetrahedron_vertices() -> Vec<Vector3<f64>> {
    vec![
        Vector3::new(1.0, 1.0, 1.0),
        Vector3::new(1.0, -1.0, -1.0),
        Vector3::new(-1.0, 1.0, -1.0),
        Vector3::new(-1.0, -1.0, 1.0),
    ]
}

/// The canonical cube's vertices `(±1, ±1, ±1)`.
pub fn cube_vertices() -> Vec<Vector3<f64>> {
    let mut out = Vec::with_capacity(8);
    for sx in [-1.0, 1.0] {
        for sy in [-1.0, 1.0] {
            for sz in [-1.0, 1.0] {
                out.push(Vector3::new(sx, sy, sz));
            }
        }
    }
    out
}

/// The canonical icosahedron's 12 vertices: cyclic permutations of `(0, ±1, ±φ)`.
pub fn icosahedron_vertices() -> Vec<Vector3<f64>> {
    let mut out = Vec::with_capacity(12);
    for s1 in [-1.0, 1.0] {
        for s2 in [-1.0, 1.0] {
            let (a, b) = (s1, s2 * GOLDEN_RATIO);
            out.push(Vector3::new(0.0, a, b));
            out.push(Vector3::new(a, b, 0.0));
            out.push(Vector3::new(b, 0.0, a));
        }
    }
    out
}

/// Whether `s` maps the point set to itself (to 1e-9).
pub fn maps_set_to_itself(s: &Rotation3<f64>, points: &[Vector3<f64>]) -> bool {
    points
        .iter()
        .all(|p| points.iter().any(|q| (s * p - q).norm() < 1e-9))
}

fn octahedral() -> Vec<Rotation3<f64>> {
    let perms = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let mut out = Vec::with_capacity(24);
    for perm in perms {
        for signs in 0..8u8 {
            let mut m = Matrix3::zeros();
            for (row, &col) in perm.iter().enumerate() {
                m[(row, col)] = if signs >> row & 1 == 1 { -1.0 } else { 1.0 };
            }
            if m.determinant() > 0.0 {
                out.push(Rotation3::from_matrix_unchecked(m));
            }
        }
    }
    // Identity first.
    out.sort_by_key(|r| (r.angle() * 1e6) as i64);
    out
}

/// The 60 rotations of the icosahedron: the closure of a 2-fold (about x), the 3-fold cyclic
/// permutation of the axes, and a 5-fold about the vertex `(0, 1, φ)`.
fn icosahedral() -> Vec<Rotation3<f64>> {
    let cyclic_perm =
        Rotation3::from_matrix_unchecked(Matrix3::new(0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0));
    let five = Rotation3::from_axis_angle(
        &Unit::new_normalize(Vector3::new(0.0, 1.0, GOLDEN_RATIO)),
        std::f64::consts::TAU / 5.0,
    );
    closure(&[rot_x(std::f64::consts::PI), cyclic_perm, five], 60)
}

/// The group generated by `generators` (breadth first), stopping at `limit` elements.
fn closure(generators: &[Rotation3<f64>], limit: usize) -> Vec<Rotation3<f64>> {
    let mut out = vec![Rotation3::identity()];
    let mut frontier = 0;
    while frontier < out.len() && out.len() < limit {
        let base = out[frontier];
        frontier += 1;
        for g in generators {
            let candidate = base * g;
            if !out.iter().any(|r| geodesic_angle(r, &candidate) < 1e-6) {
                out.push(candidate);
            }
        }
    }
    out
}

fn cyclic(n: usize) -> Vec<Rotation3<f64>> {
    (0..n)
        .map(|k| rot_z(std::f64::consts::TAU * k as f64 / n as f64))
        .collect()
}

fn with_flip(base: Vec<Rotation3<f64>>) -> Vec<Rotation3<f64>> {
    let flip = rot_x(std::f64::consts::PI);
    let flipped: Vec<_> = base.iter().map(|r| r * flip).collect();
    base.into_iter().chain(flipped).collect()
}
