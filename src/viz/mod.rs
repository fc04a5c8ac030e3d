//! The IPDF visualisation of a distribution over SO(3), drawn to an RGB image: each rotation's
//! first column (the object's x axis in the camera frame) is placed on a Mollweide projection of
//! the sphere, its colour is the tilt about that axis, and the marker's area is proportional to
//! its probability; ground truths are drawn as rings.

use image::{Rgb, RgbImage};
use nalgebra::{Rotation3, UnitQuaternion, Vector3};

/// Mollweide coordinates `(x, y)` in `[−2√2, 2√2] × [−√2, √2]` of longitude/latitude (radians).
pub fn mollweide(lon: f64, lat: f64) -> (f64, f64) {
    let target = std::f64::consts::PI * lat.sin();
    let mut t = lat;
    for _ in 0..30 {
        let f = 2.0 * t + (2.0 * t).sin() - target;
        let d = 2.0 + 2.0 * (2.0 * t).cos();
        if d.abs() < 1e-12 {
            break;
        }
        t -= f / d;
    }
    let sqrt2 = std::f64::consts::SQRT_2;
    (
        2.0 * sqrt2 / std::f64::consts::PI * lon * t.cos(),
        sqrt2 * t.sin(),
    )
}

/// Axis (first column), and tilt about it in `[0, 2π)`, of a rotation.
pub fn axis_and_tilt(r: &Rotation3<f64>) -> (Vector3<f64>, f64) {
    let axis = r * Vector3::x();
    let reference = if axis.z.abs() < 0.99 {
        Vector3::z()
    } else {
        Vector3::y()
    };
    let b1 = reference.cross(&axis).normalize();
    let b2 = axis.cross(&b1);
    let second = r * Vector3::y();
    let tilt = second.dot(&b2).atan2(second.dot(&b1));
    (axis, tilt.rem_euclid(std::f64::consts::TAU))
}

fn hue(h: f64) -> Rgb<u8> {
    let h6 = (h / std::f64::consts::TAU).fract() * 6.0;
    let x = 1.0 - (h6 % 2.0 - 1.0).abs();
    let (r, g, b) = match h6 as u32 {
        0 => (1.0, x, 0.0),
        1 => (x, 1.0, 0.0),
        2 => (0.0, 1.0, x),
        3 => (0.0, x, 1.0),
        4 => (x, 0.0, 1.0),
        _ => (1.0, 0.0, x),
    };
    Rgb([(r * 230.0) as u8, (g * 230.0) as u8, (b * 230.0) as u8])
}

fn to_rotation(q: &[f64; 4]) -> Rotation3<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3])).into()
}

/// Draws `rotations` (unit quaternions `(w, x, y, z)`) with probabilities `probabilities` (those
/// above twice the uniform probability; marker area ∝ probability), and
/// `ground_truths` as rings, on a `width`-pixel-wide image (height `width / 2`).
pub fn plot_distribution(
    rotations: &[[f64; 4]],
    probabilities: &[f64],
    ground_truths: &[[f64; 4]],
    width: u32,
) -> RgbImage {
    let width = width.max(64);
    let height = width / 2;
    let mut img = RgbImage::from_pixel(width, height, Rgb([255, 255, 255]));
    let sqrt2 = std::f64::consts::SQRT_2;
    let margin = 0.04 * width as f64;
    let scale = (width as f64 - 2.0 * margin) / (4.0 * sqrt2);
    let to_pixel = |x: f64, y: f64| {
        (
            width as f64 / 2.0 + x * scale,
            height as f64 / 2.0 - y * scale,
        )
    };
    // The sphere's outline and a light background inside it.
    for py in 0..height {
        for px in 0..width {
            let x = (px as f64 + 0.5 - width as f64 / 2.0) / scale;
            let y = (height as f64 / 2.0 - py as f64 - 0.5) / scale;
            let e = (x / (2.0 * sqrt2)).powi(2) + (y / sqrt2).powi(2);
            if e <= 1.0 {
                img.put_pixel(px, py, Rgb([240, 240, 240]));
            }
            if (e - 1.0).abs() < 2.0 / (scale * sqrt2) {
                img.put_pixel(px, py, Rgb([120, 120, 120]));
            }
        }
    }
    let max_p = probabilities.iter().cloned().fold(0.0f64, f64::max);
    let max_radius = 0.012 * width as f64;
    // As in IPDF's plots, rotations at or below twice the uniform probability are not drawn, so
    // the plot shows where the mass concentrates.
    let floor = 2.0 / probabilities.len().max(1) as f64;
    let mut order: Vec<usize> = (0..rotations.len().min(probabilities.len())).collect();
    order.sort_by(|&a, &b| probabilities[a].total_cmp(&probabilities[b]));
    for i in order {
        let p = probabilities[i];
        if p.is_nan() || p <= floor || max_p <= 0.0 {
            continue;
        }
        let radius = max_radius * (p / max_p).sqrt();
        if radius < 0.4 {
            continue;
        }
        let (axis, tilt) = axis_and_tilt(&to_rotation(&rotations[i]));
        let (x, y) = mollweide(axis.y.atan2(axis.x), axis.z.clamp(-1.0, 1.0).asin());
        let (cx, cy) = to_pixel(x, y);
        disc(&mut img, cx, cy, radius, 0.0, hue(tilt));
    }
    for gt in ground_truths {
        let (axis, tilt) = axis_and_tilt(&to_rotation(gt));
        let (x, y) = mollweide(axis.y.atan2(axis.x), axis.z.clamp(-1.0, 1.0).asin());
        let (cx, cy) = to_pixel(x, y);
        disc(
            &mut img,
            cx,
            cy,
            max_radius * 1.4,
            max_radius * 1.1,
            hue(tilt),
        );
    }
    img
}

/// Fills the ring `inner ≤ d ≤ outer` around `(cx, cy)` (a disc when `inner` is 0).
fn disc(img: &mut RgbImage, cx: f64, cy: f64, outer: f64, inner: f64, colour: Rgb<u8>) {
    let (w, h) = img.dimensions();
    let x0 = (cx - outer).floor().max(0.0) as u32;
    let y0 = (cy - outer).floor().max(0.0) as u32;
    let x1 = ((cx + outer).ceil() as u32).min(w.saturating_sub(1));
    let y1 = ((cy + outer).ceil() as u32).min(h.saturating_sub(1));
    for py in y0..=y1 {
        for px in x0..=x1 {
            let d = ((px as f64 + 0.5 - cx).powi(2) + (py as f64 + 0.5 - cy).powi(2)).sqrt();
            if d <= outer && d >= inner {
                img.put_pixel(px, py, colour);
            }
        }
    }
}
