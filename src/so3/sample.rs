//! Sampling rotations: Haar-uniform over SO(3), and uniform inside one grid cell.

use std::f64::consts::TAU;

use nalgebra::{Quaternion, Rotation3, Unit, UnitQuaternion, Vector3};
use rand::{Rng, RngExt};
use rand_distr::StandardNormal;

use super::grid::{GridLevel, pixel_frame, rot_z_matrix};

/// A Haar-uniform rotation: a normalised 4-d standard normal vector is uniform on S³, and the
/// double cover maps the uniform measure on S³ to the Haar measure on SO(3).
pub fn haar_rotation<R: Rng + ?Sized>(rng: &mut R) -> Rotation3<f64> {
    loop {
        let q: [f64; 4] = std::array::from_fn(|_| rng.sample(StandardNormal));
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm > 1e-6 {
            return UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]))
                .to_rotation_matrix();
        }
    }
}

/// `n` Haar-uniform rotations.
pub fn haar_rotations<R: Rng + ?Sized>(rng: &mut R, n: usize) -> Vec<Rotation3<f64>> {
    (0..n).map(|_| haar_rotation(rng)).collect()
}

/// A rotation uniform (Haar) inside grid cell `index` of `grid`.
///
/// The tilt is uniform in its bin; the z axis is uniform (by area) inside the HEALPix pixel,
/// drawn by rejection from a spherical cap around the pixel centre that contains the pixel (its
/// radius is 1.5× the largest centre-to-vertex angle). Uniform-in-cap then rejection outside the
/// pixel is uniform in the pixel, and the Haar measure factorises as area × tilt.
///
/// # Panics
/// If `index` is not a cell of `grid` (see [`GridLevel::check_index`]).
pub fn jitter_in_cell<R: Rng + ?Sized>(
    grid: &GridLevel,
    index: u64,
    rng: &mut R,
) -> Rotation3<f64> {
    let depth = grid.level();
    let (pixel, tilt) = (index / grid.n_tilts(), index % grid.n_tilts());
    let (lon_c, lat_c) = cdshealpix::nested::center(depth, pixel);
    let centre = unit_vector(lon_c, lat_c);
    let cap = cdshealpix::nested::vertices(depth, pixel)
        .iter()
        .map(|&(lon, lat)| centre.angle(&unit_vector(lon, lat)))
        .fold(0.0f64, f64::max)
        * 1.5;
    let cos_cap = cap.min(std::f64::consts::PI).cos();
    let frame = pixel_frame(std::f64::consts::FRAC_PI_2 - lat_c, lon_c);
    let axis = loop {
        // Uniform in the cap around +z, then moved to the pixel centre.
        let cz: f64 = rng.random_range(cos_cap..=1.0);
        let az: f64 = rng.random_range(0.0..TAU);
        let sz = (1.0 - cz * cz).max(0.0).sqrt();
        let v = frame * Vector3::new(sz * az.cos(), sz * az.sin(), cz);
        let lat = v.z.clamp(-1.0, 1.0).asin();
        let lon = v.y.atan2(v.x).rem_euclid(TAU);
        if cdshealpix::nested::hash(depth, lon, lat) == pixel {
            break v;
        }
    };
    let theta = axis.z.clamp(-1.0, 1.0).acos();
    let phi = axis.y.atan2(axis.x);
    let bin = TAU / grid.n_tilts() as f64;
    let tau = (tilt as f64 + rng.random_range(0.0..1.0)) * bin;
    // The pixel's tilt rule, τ = ψ + s·φ (grid module docs).
    let psi = tau - grid.tilt_sign(pixel) * phi;
    Rotation3::from_matrix_unchecked(pixel_frame(theta, phi) * rot_z_matrix(psi))
}

fn unit_vector(lon: f64, lat: f64) -> Vector3<f64> {
    Vector3::new(lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin())
}

/// A uniformly random unit vector (a normalised 3-d standard normal vector).
pub fn random_axis<R: Rng + ?Sized>(rng: &mut R) -> Unit<Vector3<f64>> {
    loop {
        let v: Vector3<f64> = Vector3::from_fn(|_, _| rng.sample(StandardNormal));
        if v.norm() > 1e-6 {
            return Unit::new_normalize(v);
        }
    }
}
