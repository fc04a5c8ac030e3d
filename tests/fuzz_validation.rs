//! Property tests (the fuzz target, since cargo-fuzz needs nightly): request images — random
//! bytes, mutated PNG/JPEG, raw sizes, crop boxes — and request options through the engine's
//! validation never panic, and every answer is either a correct-size crop or a named error.
//! Request messages too: valid `FrameRequest` encodings, mutated and cut, either fail to decode
//! or go through the frame path's validation (intrinsics, boxes, image) to crops or named
//! errors.
//! `PROPTEST_CASES=N` sets the number of cases (the closing note reports a long run).

mod common;

use alignist::engine::{
    CropBox, EngineError, ImageLimits, ImageRequest, PredictOptions, prepare_image,
};
use proptest::prelude::*;

fn png(w: u32, h: u32, seed: u8) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([x as u8 ^ seed, y as u8, seed.wrapping_mul(7)])
    });
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
        .unwrap();
    out
}

fn jpeg(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([x as u8, y as u8, 9]));
    let mut out = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut out),
        image::ImageFormat::Jpeg,
    )
    .unwrap();
    out
}

fn check(result: Result<Vec<u8>, EngineError>, size: u32) -> Result<(), TestCaseError> {
    match result {
        Ok(rgb) => prop_assert_eq!(rgb.len(), (size * size * 3) as usize),
        Err(EngineError::InvalidArgument { field, message })
        | Err(EngineError::ResourceExhausted { field, message }) => {
            prop_assert!(field.starts_with("image"), "{field}");
            prop_assert!(!message.is_empty());
        }
        Err(other) => prop_assert!(false, "unexpected error kind: {other}"),
    }
    Ok(())
}

fn crop_strategy() -> impl Strategy<Value = Option<CropBox>> {
    let whole = (0u32..80, 0u32..80, 0u32..80, 0u32..80)
        .prop_map(|(x, y, width, height)| CropBox::pixels(x, y, width, height));
    // Sub-pixel boxes reaching beyond the image, and any f64 at all (NaN, ±∞, huge).
    let fractional = (-100f64..200.0, -100f64..200.0, -1f64..300.0, -1f64..300.0).prop_map(
        |(x, y, width, height)| CropBox {
            x,
            y,
            width,
            height,
        },
    );
    let wild = (any::<f64>(), any::<f64>(), any::<f64>(), any::<f64>()).prop_map(
        |(x, y, width, height)| CropBox {
            x,
            y,
            width,
            height,
        },
    );
    proptest::option::of(prop_oneof![whole, fractional, wild])
}

const LIMITS: ImageLimits = ImageLimits {
    max_bytes: 64 * 1024,
    max_pixels: 128 * 128,
};

proptest! {
    #[test]
    fn random_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..4096),
                                raw in proptest::option::of((0u32..70, 0u32..70)),
                                crop in crop_strategy(), size in 1u32..48) {
        check(prepare_image(&ImageRequest { data: &data, raw_size: raw, crop }, size, &LIMITS), size)?;
    }

    #[test]
    fn mutated_images_never_panic(w in 1u32..100, h in 1u32..100, seed in any::<u8>(),
                                  use_jpeg in any::<bool>(),
                                  flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..8),
                                  cut in proptest::option::of(any::<usize>()),
                                  crop in crop_strategy(), size in 1u32..48) {
        let mut data = if use_jpeg { jpeg(w, h) } else { png(w, h, seed) };
        for (at, x) in flips {
            let n = data.len();
            data[at % n] ^= x;
        }
        if let Some(c) = cut {
            let n = data.len();
            data.truncate(c % (n + 1));
        }
        check(prepare_image(&ImageRequest { data: &data, raw_size: None, crop }, size, &LIMITS), size)?;
    }

    #[test]
    fn intact_images_inside_the_limits_are_accepted(w in 1u32..100, h in 1u32..100, seed in any::<u8>(), size in 1u32..48) {
        let data = png(w, h, seed);
        let r = prepare_image(&ImageRequest { data: &data, raw_size: None, crop: None }, size, &LIMITS);
        if w * h <= 128 * 128 && data.len() <= 64 * 1024 {
            if w.max(h) <= w.min(h) * size {
                prop_assert_eq!(r.unwrap().len(), (size * size * 3) as usize);
            } else {
                // Padded to a square it would be under one pixel across at the input.
                let elongated = matches!(&r, Err(EngineError::InvalidArgument { message, .. })
                    if message.contains("elongated"));
                prop_assert!(elongated, "not refused as elongated: {:?}", r.map(|v| v.len()));
            }
        } else {
            let exhausted = matches!(r, Err(EngineError::ResourceExhausted { .. }));
            prop_assert!(exhausted, "not RESOURCE_EXHAUSTED");
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]
    #[test]
    fn predict_options_and_depth_are_validated_without_panics(
        top_k in 0usize..100_000, level in proptest::option::of(0u8..12),
        angle in proptest::option::of(-10.0f64..400.0),
        xyz in proptest::collection::vec(prop_oneof![any::<f32>(), -2.0f32..2.0], 0..40)) {
        static ENGINE: std::sync::OnceLock<alignist::engine::Engine> = std::sync::OnceLock::new();
        let engine = ENGINE.get_or_init(|| {
            alignist::engine::Engine::load_dir(common::models_dir(), Default::default()).unwrap()
        });
        let model = engine.model("tiny").unwrap();
        let options = PredictOptions { top_k, level, mode_angle_deg: angle, ..Default::default() };
        match model.check_predict(&options) {
            Ok(l) => {
                prop_assert!(top_k >= 1 && l.level() <= 6 && l.top_k() == top_k);
            }
            Err(EngineError::InvalidArgument { field, .. }) => {
                prop_assert!(["top_k", "level", "mode_angle_deg"].contains(&field.as_str()), "{field}");
            }
            Err(e) => prop_assert!(false, "{e}"),
        }
        let object = model.object("cube").unwrap();
        match object.fusion.parse_points(&xyz, 10) {
            Ok(points) => prop_assert_eq!(points.len() * 3, xyz.len()),
            Err(EngineError::InvalidArgument { field, .. }) | Err(EngineError::ResourceExhausted { field, .. }) => {
                prop_assert_eq!(field, "depth.xyz");
            }
            Err(e) => prop_assert!(false, "{e}"),
        }
    }
}

/// A valid PredictFrame request, encoded: a 48 × 40 PNG, intrinsics, two boxes.
fn frame_message() -> Vec<u8> {
    use alignist::serve::proto::{Detection, FrameRequest, ImageInput, Intrinsics, PixelBox};
    use prost::Message;
    FrameRequest {
        model: "tiny".into(),
        image: Some(ImageInput {
            data: png(48, 40, 7),
            ..Default::default()
        }),
        intrinsics: Some(Intrinsics {
            fx: 50.0,
            fy: 50.0,
            cx: 24.0,
            cy: 20.0,
        }),
        detections: vec![
            Detection {
                bbox: Some(PixelBox {
                    x: 4.5,
                    y: 3.0,
                    width: 20.0,
                    height: 18.25,
                }),
                ..Default::default()
            },
            Detection {
                bbox: Some(PixelBox {
                    x: -10.0,
                    y: 20.0,
                    width: 30.0,
                    height: 30.0,
                }),
                object: "cube".into(),
                ..Default::default()
            },
        ],
        top_k: 3,
        ..Default::default()
    }
    .encode_to_vec()
}

proptest! {
    #[test]
    fn mutated_frame_messages_decode_or_fail_and_validate_to_crops_or_named_errors(
        flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..12),
        cut in proptest::option::of(any::<usize>()),
        tail in proptest::collection::vec(any::<u8>(), 0..16)) {
        use alignist::engine::{Intrinsics, prepare_frame};
        use alignist::serve::proto::FrameRequest;
        use prost::Message;
        let mut bytes = frame_message();
        let n = bytes.len();
        for (at, value) in flips {
            bytes[at % n] = value;
        }
        if let Some(cut) = cut {
            bytes.truncate(cut % (n + 1));
        }
        bytes.extend(tail);
        let Ok(request) = FrameRequest::decode(&bytes[..]) else {
            return Ok(());
        };
        let intrinsics = request.intrinsics.map(|i| Intrinsics { fx: i.fx, fy: i.fy, cx: i.cx, cy: i.cy });
        let image = request.image.unwrap_or_default();
        let raw_size = (image.width > 0 && image.height > 0).then_some((image.width, image.height));
        let boxes: Vec<CropBox> = request
            .detections
            .iter()
            .filter_map(|d| {
                d.bbox.map(|b| CropBox { x: b.x, y: b.y, width: b.width, height: b.height })
                    .or(d.r#box.map(|c| CropBox::pixels(c.x, c.y, c.width, c.height)))
            })
            .collect();
        let Some(intrinsics) = intrinsics else { return Ok(()); };
        let limits = ImageLimits { max_bytes: 1 << 20, max_pixels: 1 << 20 };
        let request = ImageRequest { data: &image.data, raw_size, crop: None };
        match prepare_frame(&request, &intrinsics, &boxes, 16, &limits) {
            Ok(crops) => {
                prop_assert_eq!(crops.len(), boxes.len());
                for c in &crops {
                    prop_assert_eq!(c.rgb.len(), 16 * 16 * 3);
                }
            }
            Err(EngineError::InvalidArgument { .. }) | Err(EngineError::ResourceExhausted { .. }) => {}
            Err(e) => prop_assert!(false, "{e}"),
        }
    }
}
