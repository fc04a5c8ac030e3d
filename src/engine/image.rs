//! Request images: PNG, JPEG or raw RGB8, size limits checked before decoding, an optional crop
//! box, resized to the model's square input.

use image::imageops::FilterType;
use image::{ImageReader, RgbImage};

use super::EngineError;

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
    let data = request.data;
    if data.is_empty() {
        return Err(invalid("image.data", "is empty"));
    }
    if data.len() > limits.max_bytes {
        return Err(too_large(
            "image.data",
            format!(
                "{} bytes is over the limit of {} bytes",
                data.len(),
                limits.max_bytes
            ),
        ));
    }
    let check_pixels = |w: u32, h: u32| -> Result<(), EngineError> {
        if w == 0 || h == 0 {
            return Err(invalid("image", format!("has zero size ({w}×{h})")));
        }
        if w as u64 * h as u64 > limits.max_pixels {
            return Err(too_large(
                "image",
                format!(
                    "{w}×{h} pixels is over the limit of {} pixels",
                    limits.max_pixels
                ),
            ));
        }
        Ok(())
    };
    let image = match request.raw_size {
        Some((w, h)) => {
            check_pixels(w, h)?;
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
        None => {
            let reader = ImageReader::new(std::io::Cursor::new(data))
                .with_guessed_format()
                .map_err(|e| invalid("image.data", format!("cannot be read: {e}")))?;
            if reader.format().is_none() {
                return Err(invalid(
                    "image.data",
                    "is not a PNG or JPEG image (for raw RGB8 set image.width and image.height)",
                ));
            }
            let (w, h) = reader
                .into_dimensions()
                .map_err(|e| invalid("image.data", format!("is not a valid image: {e}")))?;
            check_pixels(w, h)?;
            let mut reader = ImageReader::new(std::io::Cursor::new(data))
                .with_guessed_format()
                .map_err(|e| invalid("image.data", format!("cannot be read: {e}")))?;
            let mut decoder_limits = image::Limits::default();
            decoder_limits.max_image_width = Some(w);
            decoder_limits.max_image_height = Some(h);
            decoder_limits.max_alloc = Some(limits.max_pixels * 16);
            reader.limits(decoder_limits);
            reader
                .decode()
                .map_err(|e| invalid("image.data", format!("is not a valid image: {e}")))?
                .to_rgb8()
        }
    };
    let image = match request.crop {
        None => image,
        Some(c) => {
            if c.width == 0 || c.height == 0 {
                return Err(invalid(
                    "image.crop",
                    format!("has zero size ({}×{})", c.width, c.height),
                ));
            }
            if c.x as u64 + c.width as u64 > image.width() as u64
                || c.y as u64 + c.height as u64 > image.height() as u64
            {
                return Err(invalid(
                    "image.crop",
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
            image::imageops::crop_imm(&image, c.x, c.y, c.width, c.height).to_image()
        }
    };
    let image = if image.width() == size && image.height() == size {
        image
    } else {
        image::imageops::resize(&image, size, size, FilterType::Triangle)
    };
    Ok(image.into_raw())
}
