//! Angles and conversions between the rotation representations used on interfaces.
//!
//! Conventions (docs/DESIGN.md §1): `R` maps object coordinates to camera coordinates; quaternions
//! are `(w, x, y, z)` with `w ≥ 0`; matrices are row-major.

use nalgebra::{Matrix3, Quaternion, Rotation3, UnitQuaternion, Vector3};

use super::So3Error;

/// Geodesic angle (radians, in `[0, π]`) between two rotations: the angle of `aᵀ·b`.
///
/// Computed as `2·atan2(‖v‖, |w|)` of the relative quaternion, which stays accurate near 0 and
/// near π (unlike `acos((tr − 1) / 2)`).
pub fn geodesic_angle(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
    let rel = UnitQuaternion::from_rotation_matrix(&(a.transpose() * b));
    let q = rel.quaternion();
    2.0 * q.imag().norm().atan2(q.w.abs())
}

/// Geodesic angle (radians) between two rotations given as quaternions `(w, x, y, z)`:
/// `4·atan2(‖p − s·q‖, ‖p + s·q‖)` with `s = sign⟨p, q⟩` (the half-angle of the half-angle), which equals `2·acos(|⟨p, q⟩|)` for
/// unit quaternions but stays accurate near 0 and tolerates quaternions that are unit only to
/// rounding (e.g. read from a CSV).
#[inline]
pub fn quaternion_angle(p: &[f64; 4], q: &[f64; 4]) -> f64 {
    let s = if quaternion_dot(p, q) < 0.0 {
        -1.0
    } else {
        1.0
    };
    let (mut minus, mut plus) = (0.0, 0.0);
    for k in 0..4 {
        minus += (p[k] - s * q[k]).powi(2);
        plus += (p[k] + s * q[k]).powi(2);
    }
    4.0 * minus.sqrt().atan2(plus.sqrt())
}

/// `⟨p, q⟩` of two quaternions; `|⟨p, q⟩|` is larger the closer the rotations are.
#[inline]
pub fn quaternion_dot(p: &[f64; 4], q: &[f64; 4]) -> f64 {
    p[0] * q[0] + p[1] * q[1] + p[2] * q[2] + p[3] * q[3]
}

/// `(w, x, y, z)` with `w ≥ 0` (the canonical sign of the double cover).
pub fn to_quaternion(r: &Rotation3<f64>) -> [f64; 4] {
    let q = UnitQuaternion::from_rotation_matrix(r);
    let (w, x, y, z) = (q.w, q.i, q.j, q.k);
    if w < 0.0 {
        [-w, -x, -y, -z]
    } else {
        [w, x, y, z]
    }
}

/// Rotation from a quaternion `(w, x, y, z)`; any non-zero norm is accepted and normalised,
/// a zero or non-finite quaternion is an error.
pub fn from_quaternion(q: [f64; 4]) -> Result<Rotation3<f64>, So3Error> {
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !norm.is_finite() || norm < 1e-9 {
        return Err(So3Error::BadQuaternion(q));
    }
    let uq = UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]));
    Ok(uq.to_rotation_matrix())
}

/// Row-major entries `[r00, r01, r02, r10, …, r22]`.
pub fn to_row_major(r: &Rotation3<f64>) -> [f64; 9] {
    let m = r.matrix();
    [
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
    ]
}

/// Rotation from row-major entries. The matrix must be orthonormal with determinant +1 to
/// within `1e-4`; it is then re-orthonormalised through its quaternion (Shepperd's method, which
/// is exact for 180° rotations, where nalgebra's iterative `Rotation3::from_matrix` can stall).
pub fn from_row_major(m: [f64; 9]) -> Result<Rotation3<f64>, So3Error> {
    let mat = Matrix3::from_row_slice(&m);
    let ortho_err = (mat.transpose() * mat - Matrix3::identity()).abs().max();
    let det = mat.determinant();
    if !ortho_err.is_finite() || ortho_err > 1e-4 || (det - 1.0).abs() > 1e-4 {
        return Err(So3Error::NotARotation { det, ortho_err });
    }
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(mat));
    Ok(UnitQuaternion::new_normalize(q.into_inner()).to_rotation_matrix())
}

/// The rotation nearest (in the Frobenius norm) to the row-major matrix `m`, with `m`'s
/// orthonormality error `max |MᵀM − I|`: the polar factor `U·Vᵀ` of its SVD. Recorded poses of
/// real datasets are orthonormal only to a few 1e-3 (BOP scenes have determinants like 1.0029);
/// a matrix further than `tolerance` from a rotation, or a reflection, is refused.
pub fn nearest_rotation(m: [f64; 9], tolerance: f64) -> Result<(Rotation3<f64>, f64), So3Error> {
    let mat = Matrix3::from_row_slice(&m);
    let ortho_err = (mat.transpose() * mat - Matrix3::identity()).abs().max();
    let det = mat.determinant();
    if !ortho_err.is_finite() || ortho_err > tolerance || det <= 0.0 {
        return Err(So3Error::NotARotation { det, ortho_err });
    }
    let svd = mat.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(So3Error::NotARotation { det, ortho_err });
    };
    let polar = u * v_t;
    Ok((
        from_row_major(to_row_major(&Rotation3::from_matrix_unchecked(polar)))?,
        ortho_err,
    ))
}

/// Row-major `f32` entries, the layout of the batched encodings and the network.
pub fn to_row_major_f32(r: &Rotation3<f64>) -> [f32; 9] {
    to_row_major(r).map(|v| v as f32)
}

/// Rotation about the object z axis by `angle` radians.
pub fn rot_z(angle: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Vector3::z_axis(), angle)
}

/// Rotation about the object y axis by `angle` radians.
pub fn rot_y(angle: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Vector3::y_axis(), angle)
}

/// Rotation about the object x axis by `angle` radians.
pub fn rot_x(angle: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Vector3::x_axis(), angle)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternion_round_trip_keeps_w_non_negative() {
        let r = Rotation3::from_euler_angles(2.9, -0.4, 1.7);
        let q = to_quaternion(&r);
        assert!(q[0] >= 0.0);
        let back = from_quaternion(q).unwrap();
        assert!(geodesic_angle(&r, &back) < 1e-9);
        let neg = from_quaternion(q.map(|v| -v)).unwrap();
        assert!(geodesic_angle(&r, &neg) < 1e-9);
    }

    #[test]
    fn row_major_round_trip_and_rejects_non_rotations() {
        let r = Rotation3::from_euler_angles(0.3, 1.1, -2.0);
        let m = to_row_major(&r);
        assert!((m[1] - r.matrix()[(0, 1)]).abs() < 1e-15);
        let back = from_row_major(m).unwrap();
        assert!(geodesic_angle(&r, &back) < 1e-9);
        // 180° rotations (signed permutations) come back exactly.
        let half_turn = [-1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0];
        assert_eq!(
            to_row_major(&from_row_major(half_turn).unwrap()).map(|v| v.round()),
            half_turn
        );
        let perm = [0.0, 0.0, -1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 0.0];
        let back = to_row_major(&from_row_major(perm).unwrap());
        assert!(
            back.iter().zip(perm).all(|(a, b)| (a - b).abs() < 1e-12),
            "{back:?}"
        );
        let reflection = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0];
        assert!(from_row_major(reflection).is_err());
        assert!(from_quaternion([0.0; 4]).is_err());
    }

    #[test]
    fn angles_agree_and_are_exact_for_axis_rotations() {
        let a = Rotation3::from_euler_angles(0.2, 0.5, 0.9);
        for angle in [1e-7, 0.3, 1.0, 3.0, std::f64::consts::PI - 1e-6] {
            let b = a * rot_x(angle);
            assert!((geodesic_angle(&a, &b) - angle).abs() < 1e-9, "{angle}");
            let qa = to_quaternion(&a);
            let qb = to_quaternion(&b);
            assert!((quaternion_angle(&qa, &qb) - angle).abs() < 1e-6, "{angle}");
        }
    }
}
