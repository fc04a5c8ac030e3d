//! Object-centred crops rendered directly (fresh training and evaluation data).
//!
//! A crop is what a virtual camera looking straight at the object's centre sees, scaled so that
//! the bounding sphere's projected radius × 1.1 is half the side — the scale rule of [`super::crop`],
//! which cuts the same square out of a full render. Rendering the crop directly at
//! `size × supersample` and box-filtering it down gives an anti-aliased crop in which the object
//! covers the same pixels as a cut from a full render, without that cut's resampling blur.

use nalgebra::Rotation3;

use super::{SYMSOL_DISTANCE, symsol_pose};
use crate::cad::{Camera, Mesh, Render, RenderOptions, render};

/// Half-side of the crop around a bounding sphere of radius `radius` at distance `z`, per unit of
/// focal length (the rule of [`super::crop`]).
pub fn crop_half_side(radius: f64, z: f64) -> f64 {
    let r = radius.min(z * 0.999);
    1.1 * r / (z * z - r * r).sqrt()
}

/// The camera whose `side × side` image is the object-centred crop of a NOCS object (radius 1)
/// at the SYMSOL distance.
pub fn crop_camera(side: u32) -> Camera {
    let f = side as f64 / 2.0 / crop_half_side(1.0, SYMSOL_DISTANCE);
    Camera {
        fx: f,
        fy: f,
        ..Camera::square(side)
    }
}

/// A rendered crop: the RGB8 crop at its final size, and the full-resolution render (mask, NOCS)
/// it was filtered from.
pub struct RenderedCrop {
    /// `size² × 3` RGB8, anti-aliased.
    pub rgb: Vec<u8>,
    /// The render at `size · supersample`.
    pub render: Render,
}

/// Renders the crop of `mesh` (NOCS) at rotation `r`, `size` pixels a side, supersampled
/// `supersample`× per axis and box-filtered.
pub fn render_crop(
    mesh: &Mesh,
    r: &Rotation3<f64>,
    size: u32,
    supersample: u32,
    options: &RenderOptions,
) -> RenderedCrop {
    let ss = supersample.max(1) as usize;
    let big = size as usize * ss;
    let render = render(mesh, &crop_camera(big as u32), &symsol_pose(*r), options);
    let n = size as usize;
    let mut rgb = vec![0u8; n * n * 3];
    let area = (ss * ss) as u32;
    for y in 0..n {
        for x in 0..n {
            for c in 0..3 {
                let mut sum = 0u32;
                for dy in 0..ss {
                    let row = (y * ss + dy) * big;
                    for dx in 0..ss {
                        sum += render.rgb[(row + x * ss + dx) * 3 + c] as u32;
                    }
                }
                rgb[(y * n + x) * 3 + c] = ((sum + area / 2) / area) as u8;
            }
        }
    }
    RenderedCrop { rgb, render }
}
