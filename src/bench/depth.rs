//! What RGB-D fusion costs a request: the same whole-frame requests (a 640×480 PNG and a box,
//! top-10 to the default level) answered in-process from the image alone and with a 16-bit depth
//! PNG of the frame — decode, perspective crop, encoder and search, plus, with depth, the depth
//! decode, the back-projection and the fused search with its translation fits.

use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::cad::{RenderOptions, render};
use crate::data::virtual_crop::{frame_camera, object_pixel_box, random_placement};
use crate::engine::{
    CropBox, DepthInput, DepthRequest, ImageRequest, Intrinsics, Model, PredictOptions, SeenPoints,
    back_project, decode_depth,
};
use crate::so3::metrics::quantile;
use crate::train::data::BundleRenders;

/// One rendered RGB-D frame of one object.
struct Frame {
    object: usize,
    rgb_png: Vec<u8>,
    depth_png: Vec<u8>,
    bbox: CropBox,
}

/// Depth units per normalised object unit in the bench's PNGs (a radius is 1000 units).
const DEPTH_UNITS: f32 = 1000.0;

fn frames(
    model: &Model,
    renders: &BundleRenders,
    n: usize,
    seed: u64,
) -> anyhow::Result<Vec<Frame>> {
    let camera = frame_camera();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|i| {
            let o = i % renders.names.len();
            let mesh = &renders.fresh.meshes[o];
            let pose = random_placement(&mut rng);
            let image = render(mesh, &camera, &pose, &RenderOptions::default());
            let mut rgb_png = Vec::new();
            image::RgbImage::from_raw(camera.width, camera.height, image.rgb)
                .ok_or_else(|| anyhow::anyhow!("render size"))?
                .write_to(
                    &mut std::io::Cursor::new(&mut rgb_png),
                    image::ImageFormat::Png,
                )?;
            let depth: Vec<u16> = image
                .depth
                .iter()
                .map(|z| (z * DEPTH_UNITS).round() as u16)
                .collect();
            let mut depth_png = Vec::new();
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(camera.width, camera.height, depth)
                .ok_or_else(|| anyhow::anyhow!("render size"))?
                .write_to(
                    &mut std::io::Cursor::new(&mut depth_png),
                    image::ImageFormat::Png,
                )?;
            let [x, y, width, height] = object_pixel_box(mesh, &pose, &camera);
            Ok(Frame {
                object: model.object_index(&renders.names[o])?,
                rgb_png,
                depth_png,
                bbox: CropBox::pixels(x, y, width, height),
            })
        })
        .collect()
}

/// Prints the p50 of image-only and depth requests over `n` frames and their ratio.
pub fn depth_cost(model: &Model, renders: &BundleRenders, n: usize) -> anyhow::Result<()> {
    let frames = frames(model, renders, n.max(1), 7)?;
    let camera = frame_camera();
    let intrinsics = Intrinsics::from(&camera);
    let options = PredictOptions {
        top_k: 10,
        ..Default::default()
    };
    let (mut plain, mut fused) = (Vec::new(), Vec::new());
    // Depth requests' stages: depth decode and back-projection, then the search.
    let (mut points_ms, mut search_ms) = (Vec::new(), Vec::new());
    for round in 0..3 {
        for f in &frames {
            for with_depth in [false, true] {
                let started = Instant::now();
                let request = ImageRequest {
                    data: &f.rgb_png,
                    raw_size: None,
                    crop: None,
                };
                let crop = model
                    .prepare_frame(&request, &intrinsics, &[f.bbox])?
                    .remove(0);
                let features = model.features(&[&crop.rgb])?.swap_remove(0);
                let before_points = Instant::now();
                let seen = if with_depth {
                    let object = &model.objects[f.object];
                    let scale = object.normalisation.scale / DEPTH_UNITS as f64;
                    let depth = DepthRequest {
                        data: &f.depth_png,
                        raw_size: None,
                        scale,
                    };
                    let map = decode_depth(&depth, &model.config().image_limits)?;
                    let points = back_project(
                        &map,
                        &intrinsics,
                        &f.bbox,
                        None,
                        model.config().depth_image_points,
                        "box",
                    )?;
                    let to_virtual = crop.r_ray.inverse().cast::<f32>();
                    let seen = object.fusion.camera_points(&points, "depth.scale")?;
                    Some(SeenPoints::Camera(seen.turned(&to_virtual)))
                } else {
                    None
                };
                let depth = seen.as_ref().map(|points| DepthInput {
                    object: &model.objects[f.object],
                    points,
                });
                let before_search = Instant::now();
                let answer = model.predict(&features, &options, depth)?;
                if with_depth && round > 0 {
                    points_ms.push((before_search - before_points).as_secs_f64() * 1e3);
                    search_ms.push(before_search.elapsed().as_secs_f64() * 1e3);
                }
                std::hint::black_box(answer);
                // The first round warms caches and is not counted.
                if round > 0 {
                    let ms = started.elapsed().as_secs_f64() * 1e3;
                    if with_depth { &mut fused } else { &mut plain }.push(ms);
                }
            }
        }
    }
    let (p, d) = (quantile(&plain, 0.5), quantile(&fused, 0.5));
    println!(
        "image-only frame request p50: {p:.1} ms; with a depth image p50: {d:.1} ms ({} frames of 640×480, top-10 to the default level, {} depth points)",
        frames.len(),
        model.config().depth_image_points
    );
    println!(
        "  of a depth request (p50): depth decode and points {:.1} ms, fused search {:.1} ms",
        quantile(&points_ms, 0.5),
        quantile(&search_ms, 0.5)
    );
    println!("depth/image-only request time ratio: {:.2}", d / p);
    Ok(())
}
