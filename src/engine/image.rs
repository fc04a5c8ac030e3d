//! Request images: PNG, JPEG or raw RGB8, size limits checked before decoding, an optional box
//! of the object (cut as the crop convention's square around it), padded to a square (never
//! stretched) and resized to the model's input.

use image::imageops::FilterType;
use image::{ImageReader, RgbImage};

use super::EngineError;
use crate::data::virtual_crop::CROP_MARGIN;

/// Limits on request images.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageLimits {
    /// Most bytes of encoded (or raw) image data.
    pub max_bytes: usize,
    /// Most pixels (width × height) before cropping.
    pub max_pixels: u64,
}

impl Default for ImageLimits {
    fn default() -> Self {
        Self {
            max_bytes: 8 << 20,
            max_pixels: 4096 * 4096,
        }
    }
}

/// A pixel rectangle inside the image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CropBox {
    /// Left column.
    pub x: u32,
    /// Top row.
    pub y: u32,
    /// Width (> 0).
    pub width: u32,
    /// Height (> 0).
    pub height: u32,
}

/// An image as a request carries it.
#[derive(Debug, Clone, Copy)]
pub struct ImageRequest<'a> {
    /// PNG/JPEG bytes, or raw RGB8 when `raw_size` is given.
    pub data: &'a [u8],
    /// `(width, height)` of raw RGB8 data.
    pub raw_size: Option<(u32, u32)>,
    /// Optional crop.
    pub crop: Option<CropBox>,
}

fn invalid(field: &str, message: impl Into<String>) -> EngineError {
    EngineError::InvalidArgument {
        field: field.to_string(),
        message: message.into(),
    }
}

fn too_large(field: &str, message: impl Into<String>) -> EngineError {
    EngineError::ResourceExhausted {
        field: field.to_string(),
        message: message.into(),
    }
}

/// Decodes, crops and resizes to `size × size` RGB8 (row-major, 3 bytes per pixel).
pub fn prepare_image(
    request: &ImageRequest<'_>,
    size: u32,
    limits: &ImageLimits,
) -> Result<Vec<u8>, EngineError> {
    let image = decode_image(request, limits)?;
    let image = match request.crop {
        None => image,
        Some(c) => {
            check_box(&c, &image, "image.crop")?;
            // The crop convention's scale rule (DESIGN.md §1): a square of CROP_MARGIN × the
            // box's longer side around its centre. Without intrinsics this is a plain cut (a
            // camera looking through the image centre), black where it leaves the image.
            let side = (CROP_MARGIN * c.width.max(c.height) as f64)
                .round()
                .max(1.0) as u32;
            let cx = c.x as f64 + c.width as f64 / 2.0;
            let cy = c.y as f64 + c.height as f64 / 2.0;
            let left = (cx - side as f64 / 2.0).round() as i64;
            let top = (cy - side as f64 / 2.0).round() as i64;
            cut_square(&image, left, top, side)
        }
    };
    // Never stretch: a non-square image is padded (black) to a square around its centre.
    let image = if image.width() == image.height() {
        image
    } else {
        let side = image.width().max(image.height());
        let left = (image.width() as i64 - side as i64) / 2;
        let top = (image.height() as i64 - side as i64) / 2;
        cut_square(&image, left, top, side)
    };
    let image = if image.width() == size && image.height() == size {
        image
    } else {
        image::imageops::resize(&image, size, size, FilterType::Triangle)
    };
    Ok(image.into_raw())
}

/// Pinhole intrinsics of a full camera image, in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x (> 0).
    pub fx: f64,
    /// Focal length along y (> 0).
    pub fy: f64,
    /// Principal point, x.
    pub cx: f64,
    /// Principal point, y.
    pub cy: f64,
}

impl From<&crate::cad::Camera> for Intrinsics {
    fn from(c: &crate::cad::Camera) -> Intrinsics {
        Intrinsics {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
        }
    }
}

impl Intrinsics {
    /// Checks the values; the error names the field (`intrinsics.fx`, …).
    pub fn validate(&self) -> Result<(), EngineError> {
        for (name, v, positive) in [
            ("fx", self.fx, true),
            ("fy", self.fy, true),
            ("cx", self.cx, false),
            ("cy", self.cy, false),
        ] {
            if !v.is_finite() || (positive && v <= 0.0) {
                let need = if positive { "a positive" } else { "a finite" };
                return Err(invalid(
                    &format!("intrinsics.{name}"),
                    format!("must be {need} number of pixels, got {v}"),
                ));
            }
        }
        Ok(())
    }

    /// The row-major 3×3 matrix `K`.
    pub fn matrix(&self) -> [f64; 9] {
        [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]
    }
}

/// One detection's crop, as the network sees it, and the rotation of its virtual camera.
#[derive(Debug, Clone)]
pub struct FrameCrop {
    /// `size × size` RGB8.
    pub rgb: Vec<u8>,
    /// `R_ray`: `R_camera = R_ray · R_virtual`.
    pub r_ray: nalgebra::Rotation3<f64>,
    /// Width and height of the whole image.
    pub image_size: (u32, u32),
}

/// Decodes a full camera image once and makes the perspective crop of each box
/// ([`crate::data::virtual_crop::perspective_crop`], the training data's convention). Errors
/// name the field: `image.…`, `intrinsics.…`, `detections[i].box`.
pub fn prepare_frame(
    request: &ImageRequest<'_>,
    intrinsics: &Intrinsics,
    boxes: &[CropBox],
    size: u32,
    limits: &ImageLimits,
) -> Result<Vec<FrameCrop>, EngineError> {
    intrinsics.validate()?;
    if request.crop.is_some() {
        return Err(invalid(
            "image.crop",
            "must be unset in a frame request (the detections' boxes say where to look)",
        ));
    }
    let image = decode_image(request, limits)?;
    for (i, b) in boxes.iter().enumerate() {
        check_box(b, &image, &format!("detections[{i}].box"))?;
    }
    let k = intrinsics.matrix();
    boxes
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let bbox = [b.x as f64, b.y as f64, b.width as f64, b.height as f64];
            let (rgb, view) = crate::data::virtual_crop::perspective_crop(
                image.as_raw(),
                image.width(),
                image.height(),
                &k,
                bbox,
                size,
            )
            .ok_or_else(|| invalid(&format!("detections[{i}].box"), "has no area"))?;
            Ok(FrameCrop {
                rgb,
                r_ray: view.r_ray,
                image_size: (image.width(), image.height()),
            })
        })
        .collect()
}

/// Checks that a box has a positive size and lies inside the image.
fn check_box(c: &CropBox, image: &RgbImage, field: &str) -> Result<(), EngineError> {
    if c.width == 0 || c.height == 0 {
        return Err(invalid(
            field,
            format!("has zero size ({}×{})", c.width, c.height),
        ));
    }
    if c.x as u64 + c.width as u64 > image.width() as u64
        || c.y as u64 + c.height as u64 > image.height() as u64
    {
        return Err(invalid(
            field,
            format!(
                "({}, {}) {}×{} is not inside the {}×{} image",
                c.x,
                c.y,
                c.width,
                c.height,
                image.width(),
                image.height()
            ),
        ));
    }
    Ok(())
}

/// Checks encoded (or raw) request data against the byte limit; `field` names it.
pub(super) fn check_bytes(
    data: &[u8],
    limits: &ImageLimits,
    field: &str,
) -> Result<(), EngineError> {
    if data.is_empty() {
        return Err(invalid(field, "is empty"));
    }
    if data.len() > limits.max_bytes {
        return Err(too_large(
            field,
            format!(
                "{} bytes is over the limit of {} bytes",
                data.len(),
                limits.max_bytes
            ),
        ));
    }
    Ok(())
}

/// Checks an image size against the pixel limit; `field` names the image.
pub(super) fn check_pixels(
    w: u32,
    h: u32,
    limits: &ImageLimits,
    field: &str,
) -> Result<(), EngineError> {
    if w == 0 || h == 0 {
        return Err(invalid(field, format!("has zero size ({w}×{h})")));
    }
    if w as u64 * h as u64 > limits.max_pixels {
        return Err(too_large(
            field,
            format!(
                "{w}×{h} pixels is over the limit of {} pixels",
                limits.max_pixels
            ),
        ));
    }
    Ok(())
}

/// Decodes an encoded image whose size is checked against the limits before any pixel is
/// decoded (and the decoder bounded to that size); `field` names the data, `image` the image,
/// `raw` the raw pixel format the request could have sent instead.
pub(super) fn decode_within(
    data: &[u8],
    limits: &ImageLimits,
    field: &str,
    image: &str,
    raw: &str,
) -> Result<image::DynamicImage, EngineError> {
    let reader = ImageReader::new(std::io::Cursor::new(data))
        .with_guessed_format()
        .map_err(|e| invalid(field, format!("cannot be read: {e}")))?;
    if reader.format().is_none() {
        return Err(invalid(
            field,
            format!(
                "is not a PNG or JPEG image (for raw {raw} set {image}.width and {image}.height)"
            ),
        ));
    }
    let (w, h) = reader
        .into_dimensions()
        .map_err(|e| invalid(field, format!("is not a valid image: {e}")))?;
    check_pixels(w, h, limits, image)?;
    let mut reader = ImageReader::new(std::io::Cursor::new(data))
        .with_guessed_format()
        .map_err(|e| invalid(field, format!("cannot be read: {e}")))?;
    let mut decoder_limits = image::Limits::default();
    decoder_limits.max_image_width = Some(w);
    decoder_limits.max_image_height = Some(h);
    decoder_limits.max_alloc = Some(limits.max_pixels * 16);
    reader.limits(decoder_limits);
    reader
        .decode()
        .map_err(|e| invalid(field, format!("is not a valid image: {e}")))
}

/// Decodes PNG/JPEG or raw RGB8 within the limits (checked before decoding).
fn decode_image(request: &ImageRequest<'_>, limits: &ImageLimits) -> Result<RgbImage, EngineError> {
    let data = request.data;
    check_bytes(data, limits, "image.data")?;
    Ok(match request.raw_size {
        Some((w, h)) => {
            check_pixels(w, h, limits, "image")?;
            let expected = w as u64 * h as u64 * 3;
            if data.len() as u64 != expected {
                return Err(invalid(
                    "image.data",
                    format!(
                        "raw RGB8 of {w}×{h} needs {expected} bytes, got {}",
                        data.len()
                    ),
                ));
            }
            RgbImage::from_raw(w, h, data.to_vec())
                .ok_or_else(|| invalid("image.data", "raw RGB8 does not fit its size"))?
        }
        None => decode_within(data, limits, "image.data", "image", "RGB8")?.to_rgb8(),
    })
}

/// The `side × side` square of `image` whose top-left corner is `(left, top)` (which may lie
/// outside the image); black where it leaves the image.
fn cut_square(image: &RgbImage, left: i64, top: i64, side: u32) -> RgbImage {
    let mut out = RgbImage::new(side, side);
    image::imageops::overlay(&mut out, image, -left, -top);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raw(w: u32, h: u32, f: impl Fn(u32, u32) -> [u8; 3]) -> Vec<u8> {
        let f = &f;
        (0..h)
            .flat_map(|y| (0..w).flat_map(move |x| f(x, y)))
            .collect()
    }

    #[test]
    fn non_square_images_are_padded_not_stretched() {
        // A white 40×20 image: padded to 40×40, the top and bottom quarters are black.
        let data = raw(40, 20, |_, _| [255, 255, 255]);
        let request = ImageRequest {
            data: &data,
            raw_size: Some((40, 20)),
            crop: None,
        };
        let out = prepare_image(&request, 40, &ImageLimits::default()).unwrap();
        let at = |x: usize, y: usize| out[(y * 40 + x) * 3];
        assert_eq!(at(20, 2), 0);
        assert_eq!(at(20, 37), 0);
        assert_eq!(at(20, 20), 255);
        assert_eq!(at(1, 20), 255);
    }

    #[test]
    fn a_box_is_cut_as_the_square_of_the_crop_convention() {
        // A white 10×20 box at (20, 10) in a black 60×40 image: the crop is the 24×24 square
        // around its centre (25, 20), so the box spans the middle 10/24 of the crop's width.
        let data = raw(60, 40, |x, y| {
            if (20..30).contains(&x) && (10..30).contains(&y) {
                [255, 255, 255]
            } else {
                [0, 0, 0]
            }
        });
        let request = ImageRequest {
            data: &data,
            raw_size: Some((60, 40)),
            crop: Some(CropBox {
                x: 20,
                y: 10,
                width: 10,
                height: 20,
            }),
        };
        let out = prepare_image(&request, 24, &ImageLimits::default()).unwrap();
        let white: Vec<usize> = (0..24).filter(|&x| out[(12 * 24 + x) * 3] > 128).collect();
        assert_eq!(white, (7..17).collect::<Vec<_>>());
        let column: Vec<usize> = (0..24).filter(|&y| out[(y * 24 + 12) * 3] > 128).collect();
        assert_eq!(column, (2..22).collect::<Vec<_>>());
    }
}
