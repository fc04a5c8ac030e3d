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

/// A box around the object in image pixels, with sub-pixel precision as detectors give it. It
/// may extend beyond the image (an object cut by the frame's edge: the crop is black there) but
/// must overlap it ([`CropBox::check`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CropBox {
    /// Left edge (pixel `u` covers `[u, u + 1)`).
    pub x: f64,
    /// Top edge.
    pub y: f64,
    /// Width (> 0).
    pub width: f64,
    /// Height (> 0).
    pub height: f64,
}

/// How far a box may reach beyond the image, in image sides: further out it is no detection.
const BOX_REACH: f64 = 4.0;

impl CropBox {
    /// The box of whole pixels `(x, y)` … `(x + width, y + height)`.
    pub fn pixels(x: u32, y: u32, width: u32, height: u32) -> CropBox {
        CropBox {
            x: x as f64,
            y: y as f64,
            width: width as f64,
            height: height as f64,
        }
    }

    /// `[x, y, width, height]`.
    pub fn as_array(&self) -> [f64; 4] {
        [self.x, self.y, self.width, self.height]
    }

    /// Checks that the box is finite, has a positive size, overlaps the `width × height` image
    /// and reaches no further than [`BOX_REACH`] image sides beyond it; `field` names it.
    pub fn check(&self, width: u32, height: u32, field: &str) -> Result<(), EngineError> {
        let (w, h) = (width as f64, height as f64);
        let side = w.max(h);
        let describe = || format!("({}, {}) {}×{}", self.x, self.y, self.width, self.height);
        if !self.as_array().iter().all(|v| v.is_finite()) {
            return Err(invalid(field, format!("{} is not finite", describe())));
        }
        if self.width <= 0.0 || self.height <= 0.0 {
            return Err(invalid(field, format!("{} has no area", describe())));
        }
        if self.x >= w || self.y >= h || self.x + self.width <= 0.0 || self.y + self.height <= 0.0 {
            return Err(invalid(
                field,
                format!("{} does not overlap the {width}×{height} image", describe()),
            ));
        }
        let reach = BOX_REACH * side;
        if self.width > reach
            || self.height > reach
            || self.x < -reach
            || self.y < -reach
            || self.x + self.width > w + reach
            || self.y + self.height > h + reach
        {
            return Err(invalid(
                field,
                format!(
                    "{} reaches more than {BOX_REACH} image sides beyond the {width}×{height} image",
                    describe()
                ),
            ));
        }
        Ok(())
    }

    /// The whole pixels whose centres lie inside the box and the `width × height` image:
    /// `(u0, v0, u1, v1)`, end exclusive (empty ranges when none).
    pub fn pixel_span(&self, width: u32, height: u32) -> (usize, usize, usize, usize) {
        let span = |lo: f64, len: f64, n: u32| {
            let a = (lo - 0.5).ceil().clamp(0.0, n as f64) as usize;
            let b = ((lo + len - 0.5).ceil()).clamp(0.0, n as f64) as usize;
            (a, b.max(a))
        };
        let (u0, u1) = span(self.x, self.width, width);
        let (v0, v1) = span(self.y, self.height, height);
        (u0, v0, u1, v1)
    }
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
    let (left, top, side) = match request.crop {
        // Never stretch: a non-square image is padded (black) to a square around its centre.
        None => {
            let (long, short) = (
                image.width().max(image.height()),
                image.width().min(image.height()),
            );
            if long as u64 > short as u64 * size as u64 {
                return Err(invalid(
                    "image",
                    format!(
                        "{}×{} pixels is too elongated: padded to a square it would be under one \
                         pixel across at the model's {size}×{size} input (send image.crop, the \
                         object's box)",
                        image.width(),
                        image.height()
                    ),
                ));
            }
            let side = long;
            let left = (image.width() as i64 - side as i64) / 2;
            let top = (image.height() as i64 - side as i64) / 2;
            (left, top, side)
        }
        Some(c) => {
            c.check(image.width(), image.height(), "image.crop")?;
            // The crop convention's scale rule (docs/DESIGN.md §1): a square of CROP_MARGIN × the
            // box's longer side around its centre. Without intrinsics this is a plain cut (a
            // camera looking through the image centre), black where it leaves the image.
            let side = (CROP_MARGIN * c.width.max(c.height)).round().max(1.0) as u32;
            let cx = c.x + c.width / 2.0;
            let cy = c.y + c.height / 2.0;
            let left = (cx - side as f64 / 2.0).round() as i64;
            let top = (cy - side as f64 / 2.0).round() as i64;
            (left, top, side)
        }
    };
    Ok(square_resized(&image, left, top, side, size).into_raw())
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

    /// Checks the values against a `width × height` image: focal lengths within 1/100 ..= 100
    /// times its longer side, the principal point within one image size of the image. Values
    /// outside are no camera's (5e-324 passes the positive check and turns every answer to NaN).
    pub fn validate_for(&self, width: u32, height: u32) -> Result<(), EngineError> {
        self.validate()?;
        let side = width.max(height) as f64;
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(side / 100.0..=side * 100.0).contains(&v) {
                return Err(invalid(
                    &format!("intrinsics.{name}"),
                    format!(
                        "{v} pixels is no focal length for a {width}×{height} image (expected \
                         {} ..= {})",
                        side / 100.0,
                        side * 100.0
                    ),
                ));
            }
        }
        for (name, v, extent) in [
            ("cx", self.cx, width as f64),
            ("cy", self.cy, height as f64),
        ] {
            if !(-extent..=2.0 * extent).contains(&v) {
                return Err(invalid(
                    &format!("intrinsics.{name}"),
                    format!(
                        "{v} pixels is more than one image size from the {width}×{height} image"
                    ),
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
    intrinsics.validate_for(image.width(), image.height())?;
    for (i, b) in boxes.iter().enumerate() {
        b.check(
            image.width(),
            image.height(),
            &format!("detections[{i}].box"),
        )?;
    }
    let k = intrinsics.matrix();
    boxes
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let (rgb, view) = crate::data::virtual_crop::perspective_crop(
                image.as_raw(),
                image.width(),
                image.height(),
                &k,
                b.as_array(),
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
    if image::guess_format(data).ok() == Some(image::ImageFormat::Jpeg) && !jpeg_is_complete(data) {
        return Err(invalid(
            field,
            "is a truncated JPEG (no end-of-image marker after its last scan)",
        ));
    }
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

/// Whether a JPEG's last scan (`FF DA`) is followed by the end-of-image marker (`FF D9`): the
/// decoder fills a cut-off scan with grey and reports nothing.
fn jpeg_is_complete(data: &[u8]) -> bool {
    let last_scan = data.windows(2).rposition(|w| w == [0xFF, 0xDA]);
    let end = data.windows(2).rposition(|w| w == [0xFF, 0xD9]);
    matches!((last_scan, end), (Some(s), Some(e)) if e > s)
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
/// outside the image), black where it leaves the image, resized to `size × size`.
///
/// The square itself is never allocated: only the part of the image inside it is resized (to its
/// share of the output) and placed on a black `size × size` canvas. Memory and time are bounded
/// by the decoded image and the output, whatever the padding (a 1 048 576 × 1 image pads to a
/// square of 3.3 TB of RGB8; this makes 32 × 32 × 3 bytes of it).
fn square_resized(image: &RgbImage, left: i64, top: i64, side: u32, size: u32) -> RgbImage {
    let mut out = RgbImage::new(size, size);
    let (w, h) = (image.width() as i64, image.height() as i64);
    let (x0, x1) = (left.max(0), (left + side as i64).min(w));
    let (y0, y1) = (top.max(0), (top + side as i64).min(h));
    if x0 >= x1 || y0 >= y1 {
        return out;
    }
    let scale = size as f64 / side as f64;
    // The visible part's place on the canvas, at least one output pixel on each axis.
    let place = |from: i64, to: i64, origin: i64| {
        let a = (((from - origin) as f64 * scale).round() as i64).clamp(0, size as i64 - 1);
        let b = (((to - origin) as f64 * scale).round() as i64).clamp(a + 1, size as i64);
        (a, (b - a) as u32)
    };
    let (dx, dw) = place(x0, x1, left);
    let (dy, dh) = place(y0, y1, top);
    let visible = image::imageops::crop_imm(
        image,
        x0 as u32,
        y0 as u32,
        (x1 - x0) as u32,
        (y1 - y0) as u32,
    );
    let resized = if (dw as i64, dh as i64) == (x1 - x0, y1 - y0) {
        visible.to_image()
    } else {
        image::imageops::resize(&*visible, dw, dh, FilterType::Triangle)
    };
    image::imageops::replace(&mut out, &resized, dx, dy);
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
    fn a_long_thin_image_is_refused_or_cut_without_allocating_its_square() {
        // 1 048 576 × 1 is under the pixel limit; its padded square (3.3 TB of RGB8) must never
        // be made. Whole, it is refused: at the input it would be under one pixel high.
        let (w, h) = (1 << 20, 1);
        let data = vec![255u8; w * h * 3];
        let request = ImageRequest {
            data: &data,
            raw_size: Some((w as u32, h as u32)),
            crop: None,
        };
        let err = prepare_image(&request, 32, &ImageLimits::default()).unwrap_err();
        assert!(
            matches!(&err, EngineError::InvalidArgument { field, .. } if field == "image"),
            "{err:?}"
        );
        // 64 × 2 at a 32-pixel input is one output row: padded, not refused.
        let data = vec![255u8; 64 * 2 * 3];
        let thin = ImageRequest {
            data: &data,
            raw_size: Some((64, 2)),
            crop: None,
        };
        let out = prepare_image(&thin, 32, &ImageLimits::default()).unwrap();
        let bright: Vec<usize> = (0..32).filter(|&y| out[(y * 32 + 5) * 3] > 128).collect();
        assert_eq!(bright, vec![16]);
        // A box of the whole long row: its square (1.2 × 1 048 576) is cut without being made.
        let request = ImageRequest {
            crop: Some(CropBox::pixels(0, 0, w as u32, 1)),
            ..request
        };
        let out = prepare_image(&request, 32, &ImageLimits::default()).unwrap();
        assert_eq!(out.len(), 32 * 32 * 3);
        assert!(out.iter().any(|&v| v > 128));
    }

    #[test]
    fn boxes_may_be_fractional_and_reach_beyond_the_image_but_must_overlap_it() {
        let data = vec![255u8; 60 * 40 * 3];
        let request = |b: CropBox| ImageRequest {
            data: &data,
            raw_size: Some((60, 40)),
            crop: Some(b),
        };
        let limits = ImageLimits::default();
        // Half outside on the left: the crop's left part is black, its right part white.
        let cut = CropBox {
            x: -10.5,
            y: 10.25,
            width: 21.0,
            height: 20.0,
        };
        let out = prepare_image(&request(cut), 24, &limits).unwrap();
        let row: Vec<u8> = (0..24).map(|x| out[(12 * 24 + x) * 3]).collect();
        assert_eq!(row[2], 0, "{row:?}");
        assert_eq!(row[21], 255, "{row:?}");
        for (bad, what) in [
            (CropBox { x: 61.0, ..cut }, "does not overlap"),
            (CropBox { width: 0.0, ..cut }, "no area"),
            (CropBox { y: f64::NAN, ..cut }, "not finite"),
            (CropBox { width: 1e9, ..cut }, "beyond"),
        ] {
            let err = prepare_image(&request(bad), 24, &limits).unwrap_err();
            assert!(err.to_string().contains(what), "{bad:?}: {err}");
        }
        // The pixels of a box are those whose centres it holds, inside the image.
        assert_eq!(cut.pixel_span(60, 40), (0, 10, 10, 30));
    }

    #[test]
    fn truncated_jpegs_and_intrinsics_of_no_camera_are_refused() {
        let img =
            image::RgbImage::from_fn(40, 30, |x, y| image::Rgb([x as u8 * 6, y as u8 * 8, 90]));
        let mut jpeg = Vec::new();
        img.write_to(
            &mut std::io::Cursor::new(&mut jpeg),
            image::ImageFormat::Jpeg,
        )
        .unwrap();
        let request = |data: &[u8]| {
            let request = ImageRequest {
                data,
                raw_size: None,
                crop: None,
            };
            prepare_image(&request, 16, &ImageLimits::default())
        };
        assert!(request(&jpeg).is_ok());
        // Cut in the middle of the scan, where the decoder would fill the rest with grey.
        let scan = jpeg.windows(2).position(|w| w == [0xFF, 0xDA]).unwrap();
        let err = request(&jpeg[..scan + (jpeg.len() - scan) / 2]).unwrap_err();
        assert!(err.to_string().contains("truncated"), "{err}");
        let k = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
        };
        assert!(k.validate_for(640, 480).is_ok());
        for (bad, field) in [
            (Intrinsics { fx: 5e-324, ..k }, "intrinsics.fx"),
            (Intrinsics { fy: 1e9, ..k }, "intrinsics.fy"),
            (Intrinsics { cx: -1e9, ..k }, "intrinsics.cx"),
            (Intrinsics { cy: f64::NAN, ..k }, "intrinsics.cy"),
        ] {
            let err = bad.validate_for(640, 480).unwrap_err();
            assert!(
                matches!(&err, EngineError::InvalidArgument { field: f, .. } if f == field),
                "{err:?}"
            );
        }
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
            crop: Some(CropBox::pixels(20, 10, 10, 20)),
        };
        let out = prepare_image(&request, 24, &ImageLimits::default()).unwrap();
        let white: Vec<usize> = (0..24).filter(|&x| out[(12 * 24 + x) * 3] > 128).collect();
        assert_eq!(white, (7..17).collect::<Vec<_>>());
        let column: Vec<usize> = (0..24).filter(|&y| out[(y * 24 + 12) * 3] > 128).collect();
        assert_eq!(column, (2..22).collect::<Vec<_>>());
    }
}
