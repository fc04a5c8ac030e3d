//! Depth images as a camera gives them: a 16-bit depth map registered to the colour image,
//! decoded within the image limits and back-projected, inside a detection's box (and mask), to
//! camera-frame points.
//!
//! Pixel `(u, v)` (column, row; the top-left pixel's centre at `(0.5, 0.5)`, as the intrinsics
//! convention of the frame requests) with depth `z` along the optical axis is the point
//! `z · ((u + 0.5 − cx)/fx, (v + 0.5 − cy)/fy, 1)`. A depth value of 0 is "no measurement".

use nalgebra::Vector3;

use super::image::{CropBox, ImageLimits, Intrinsics, check_bytes, check_pixels, decode_within};
use super::{EngineError, invalid};

/// A decoded depth map, in the object's mesh units (0 where the camera measured nothing).
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Depth along the optical axis per pixel, row-major, in mesh units.
    pub values: Vec<f32>,
}

/// A depth image as a request carries it.
#[derive(Debug, Clone, Copy)]
pub struct DepthRequest<'a> {
    /// A 16-bit single-channel PNG, or raw little-endian `u16` values when `raw_size` is given.
    pub data: &'a [u8],
    /// `(width, height)` of raw data.
    pub raw_size: Option<(u32, u32)>,
    /// Mesh units per depth unit (e.g. 0.1 for a PNG in 0.1 mm with a mesh in millimetres).
    pub scale: f64,
}

/// Decodes a depth image within `limits`; errors name the field (`depth.data`, `depth.scale`, …).
pub fn decode_depth(
    request: &DepthRequest<'_>,
    limits: &ImageLimits,
) -> Result<DepthMap, EngineError> {
    if !(request.scale.is_finite() && request.scale > 0.0) {
        return Err(invalid(
            "depth.scale",
            format!(
                "must be a positive number of mesh units per depth unit, got {}",
                request.scale
            ),
        ));
    }
    let data = request.data;
    check_bytes(data, limits, "depth.data")?;
    let (width, height, raw): (u32, u32, Vec<u16>) = match request.raw_size {
        Some((w, h)) => {
            check_pixels(w, h, limits, "depth")?;
            let expected = w as u64 * h as u64 * 2;
            if data.len() as u64 != expected {
                return Err(invalid(
                    "depth.data",
                    format!(
                        "raw depth of {w}×{h} needs {expected} bytes (little-endian u16), got {}",
                        data.len()
                    ),
                ));
            }
            let values = data
                .chunks_exact(2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]))
                .collect();
            (w, h, values)
        }
        None => match decode_within(data, limits, "depth.data", "depth", "u16")? {
            image::DynamicImage::ImageLuma16(gray) => {
                (gray.width(), gray.height(), gray.into_raw())
            }
            other => {
                return Err(invalid(
                    "depth.data",
                    format!(
                        "must be a 16-bit single-channel PNG (or raw u16), got {:?}",
                        other.color()
                    ),
                ));
            }
        },
    };
    let scale = request.scale as f32;
    Ok(DepthMap {
        width,
        height,
        values: raw.into_iter().map(|v| v as f32 * scale).collect(),
    })
}

/// The valid depth pixels of an object back-projected to the camera frame (mesh units).
#[derive(Debug, Clone, PartialEq)]
pub struct BackProjected {
    /// At most the asked number of them, evenly spaced in pixel order (deterministic): the points
    /// the SDF expert scores.
    pub points: Vec<Vector3<f64>>,
    /// The centroid of all of them, each weighed by `z²` (its surface area seen head-on): the
    /// translation estimate's anchor, free of the subsample's noise (256 points put it off by
    /// ~3 % of the radius).
    pub centroid: Vector3<f64>,
}

/// The valid depth pixels inside `bbox` and, when given, inside `mask` (row-major over the whole
/// image, `true` on the object), back-projected with `intrinsics` (pixel centres at +0.5; 0 is no
/// measurement): at most `max_points` points, and the centroid of all. `field` names the box in
/// errors.
pub fn back_project(
    map: &DepthMap,
    intrinsics: &Intrinsics,
    bbox: &CropBox,
    mask: Option<&[bool]>,
    max_points: usize,
    field: &str,
) -> Result<BackProjected, EngineError> {
    bbox.check(map.width, map.height, field)?;
    let (u0, v0, u1, v1) = bbox.pixel_span(map.width, map.height);
    let w = map.width as usize;
    let mut valid = Vec::new();
    for v in v0..v1 {
        for u in u0..u1 {
            let i = v * w + u;
            let z = map.values[i];
            if z > 0.0 && z.is_finite() && mask.is_none_or(|m| m[i]) {
                valid.push(i);
            }
        }
    }
    if valid.is_empty() {
        return Err(invalid(
            field,
            "holds no valid depth (every pixel inside it is 0 or outside the mask)",
        ));
    }
    let point = |i: usize| {
        let (u, v) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        let z = map.values[i] as f64;
        Vector3::new(
            z * (u - intrinsics.cx) / intrinsics.fx,
            z * (v - intrinsics.cy) / intrinsics.fy,
            z,
        )
    };
    let (mut sum, mut weight) = (Vector3::zeros(), 0.0);
    for &i in &valid {
        let p = point(i);
        sum += p * (p.z * p.z);
        weight += p.z * p.z;
    }
    let n = valid.len().min(max_points.max(1));
    Ok(BackProjected {
        points: (0..n).map(|k| point(valid[k * valid.len() / n])).collect(),
        centroid: sum / weight,
    })
}

/// Decodes a mask PNG of `width × height` within `limits` (non-zero: the object); `field` names
/// it.
pub fn decode_mask(
    data: &[u8],
    width: u32,
    height: u32,
    limits: &ImageLimits,
    field: &str,
) -> Result<Vec<bool>, EngineError> {
    check_bytes(data, limits, field)?;
    let image = decode_within(data, limits, field, field, "pixels (no raw masks)")?.into_luma8();
    if image.width() != width || image.height() != height {
        return Err(invalid(
            field,
            format!(
                "is {}×{}, not the image's {width}×{height}",
                image.width(),
                image.height()
            ),
        ));
    }
    Ok(image.into_raw().into_iter().map(|v| v > 0).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plane(width: u32, height: u32, z: f32) -> DepthMap {
        DepthMap {
            width,
            height,
            values: vec![z; (width * height) as usize],
        }
    }

    const K: Intrinsics = Intrinsics {
        fx: 2.0,
        fy: 4.0,
        cx: 2.0,
        cy: 2.0,
    };

    #[test]
    fn back_projection_inverts_the_pinhole_projection_at_pixel_centres() {
        let mut map = plane(4, 4, 2.0);
        map.values[5] = 0.0; // (1, 1): no measurement
        let whole = CropBox::pixels(0, 0, 4, 4);
        let seen = back_project(&map, &K, &whole, None, 100, "box").unwrap();
        let points = &seen.points;
        assert_eq!(points.len(), 15);
        // Pixel (0, 0) has its centre at (0.5, 0.5).
        assert_eq!(
            points[0],
            Vector3::new(2.0 * -1.5 / 2.0, 2.0 * -1.5 / 4.0, 2.0)
        );
        for p in points {
            let (u, v) = (K.fx * p.x / p.z + K.cx, K.fy * p.y / p.z + K.cy);
            assert!((u.fract() - 0.5).abs() < 1e-9 && (v.fract() - 0.5).abs() < 1e-9);
        }
        // A mask keeps its pixels only; a cap keeps evenly spaced ones.
        let mut mask = vec![false; 16];
        mask[15] = true;
        let masked = back_project(&map, &K, &whole, Some(&mask), 100, "box").unwrap();
        assert_eq!(
            masked.points,
            vec![Vector3::new(2.0 * 1.5 / 2.0, 2.0 * 1.5 / 4.0, 2.0)]
        );
        assert_eq!(masked.centroid, masked.points[0]);
        // A cap keeps 4 of the 15 points, and the centroid of all 15.
        let capped = back_project(&map, &K, &whole, None, 4, "box").unwrap();
        assert_eq!(capped.points.len(), 4);
        assert_eq!(capped.centroid, seen.centroid);
        let mean = points.iter().sum::<Vector3<f64>>() / 15.0; // all at z = 2: equal weights
        assert!((seen.centroid - mean).norm() < 1e-12);
        // Nothing valid, or a box outside the map: an error naming the box.
        let empty = back_project(&plane(4, 4, 0.0), &K, &whole, None, 100, "det.box");
        assert!(empty.unwrap_err().to_string().starts_with("det.box"));
        let outside = CropBox { x: 4.5, ..whole };
        let e = back_project(&map, &K, &outside, None, 100, "det.box").unwrap_err();
        assert!(e.to_string().starts_with("det.box"));
    }

    #[test]
    fn depth_images_decode_from_16_bit_png_or_raw_and_bad_ones_name_the_field() {
        let limits = ImageLimits::default();
        let values: Vec<u16> = (0..12).map(|v| v * 100).collect();
        let mut png = Vec::new();
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(4, 3, values.clone())
            .unwrap()
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let request = DepthRequest {
            data: &png,
            raw_size: None,
            scale: 0.5,
        };
        let map = decode_depth(&request, &limits).unwrap();
        assert_eq!((map.width, map.height), (4, 3));
        assert_eq!(map.values[3], 150.0);
        let raw: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let from_raw = DepthRequest {
            data: &raw,
            raw_size: Some((4, 3)),
            scale: 0.5,
        };
        assert_eq!(decode_depth(&from_raw, &limits).unwrap(), map);

        let mut gray8 = Vec::new();
        image::GrayImage::new(4, 3)
            .write_to(
                &mut std::io::Cursor::new(&mut gray8),
                image::ImageFormat::Png,
            )
            .unwrap();
        let field = |r: DepthRequest<'_>| {
            let e = decode_depth(&r, &limits).unwrap_err().to_string();
            e[..e.find(':').unwrap()].to_string()
        };
        assert_eq!(
            field(DepthRequest {
                data: &gray8,
                ..request
            }),
            "depth.data"
        );
        assert_eq!(
            field(DepthRequest {
                data: &raw[1..],
                ..from_raw
            }),
            "depth.data"
        );
        assert_eq!(
            field(DepthRequest {
                scale: -1.0,
                ..request
            }),
            "depth.scale"
        );
        assert_eq!(
            field(DepthRequest {
                scale: f64::NAN,
                ..request
            }),
            "depth.scale"
        );
        assert_eq!(
            field(DepthRequest {
                data: &[],
                ..request
            }),
            "depth.data"
        );
    }
}
