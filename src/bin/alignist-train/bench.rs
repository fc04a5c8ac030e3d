//! `alignist-train bench`: performance figures of a bundle.

use std::path::Path;

use anyhow::{Context, Result};

pub(crate) fn bench_cmd(bundle: &Path, count: usize) -> Result<()> {
    let loaded = alignist::bundle::model::ModelBundle::load(bundle)
        .with_context(|| format!("--model {}", bundle.display()))?;
    let size = loaded.manifest.network.image_size;
    let mesh = &loaded.experts[0].mesh;
    let camera = alignist::cad::Camera::square(size);
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(99);
    let images: Vec<Vec<u8>> = alignist::so3::haar_rotations(&mut rng, count.max(1))
        .into_iter()
        .map(|r| {
            let rgb = alignist::cad::render(
                mesh,
                &camera,
                &alignist::data::symsol_pose(r),
                &alignist::cad::RenderOptions::default(),
            )
            .rgb;
            let mut png = Vec::new();
            image::RgbImage::from_raw(size, size, rgb)
                .context("render size")?
                .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
            Ok(png)
        })
        .collect::<Result<_>>()?;
    drop(loaded);
    alignist::serve::bench::bench(bundle, &images)
}
