//! Realistic crops of the five SYMSOL-I shapes (or of the parts whose mesh files follow), as the
//! trainer and `eval --realistic` make them: a mosaic PNG per split (rows: objects; 12 crops
//! each) and the time per crop beside the flat renders'.
//! `cargo run --release --example probe_realism -- [SIZE] [OUT_DIR] [MESH…]`; `ROUNDS=N` times
//! N rounds of the 12 crops per object (the mosaic shows the first).
use std::time::Instant;

use alignist::cad::Shape;
use alignist::data::realism::{Realism, SceneAssets, realistic_crop};
use alignist::train::data::FreshRenders;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let size: u32 = args.next().map_or(Ok(64), |s| s.parse())?;
    let out = std::path::PathBuf::from(args.next().unwrap_or_else(|| "target".into()));
    let parts: Vec<String> = args.collect();
    let meshes: Vec<_> = if parts.is_empty() {
        [
            Shape::Tetrahedron,
            Shape::Cube,
            Shape::Icosahedron,
            Shape::Cone,
            Shape::Cylinder,
        ]
        .iter()
        .map(|s| s.mesh())
        .collect()
    } else {
        parts
            .iter()
            .map(|p| Ok(alignist::cad::load_part(std::path::Path::new(p), None)?.1))
            .collect::<anyhow::Result<_>>()?
    };
    let rounds: u64 = std::env::var("ROUNDS").map_or(Ok(1), |r| r.parse())?;
    let per_row = 12u32;
    for (name, realism) in [
        ("train", Realism::TRAIN),
        ("held-out", Realism::HELD_OUT),
        ("held-out-boxes", Realism::held_out_boxes(0.08)),
    ] {
        let assets = SceneAssets::new(&meshes, realism);
        let mut mosaic = image::RgbImage::new(size * per_row, size * meshes.len() as u32);
        let (mut visible, mut count) = (0.0, 0);
        let started = Instant::now();
        for (i, _) in meshes.iter().enumerate() {
            for j in 0..per_row as u64 * rounds {
                let mut rng = ChaCha8Rng::seed_from_u64(((i as u64) << 32) | j);
                let crop = realistic_crop(&assets, i, size, 2, &mut rng);
                visible += crop.visible_fraction;
                count += 1;
                if j >= per_row as u64 {
                    continue;
                }
                let j = j as u32;
                let tile = image::RgbImage::from_raw(size, size, crop.rgb).expect("size² × 3");
                image::imageops::replace(
                    &mut mosaic,
                    &tile,
                    (j * size) as i64,
                    (i as u32 * size) as i64,
                );
            }
        }
        let ms = started.elapsed().as_secs_f64() * 1e3 / count as f64;
        let path = out.join(format!("realism-{name}.png"));
        mosaic.save(&path)?;
        println!(
            "{name:15} {ms:6.2} ms per {size}px crop (supersample 2, one core); mean visible fraction {:.2}; {}",
            visible / count as f64,
            path.display()
        );
    }
    let fresh = FreshRenders {
        meshes,
        supersample: 2,
        pool: None,
        realism: None,
    };
    let started = Instant::now();
    let n = 60;
    for s in 0..n {
        let object = s % fresh.meshes.len();
        let _ = fresh.training_image(object, size, None, &mut ChaCha8Rng::seed_from_u64(s as u64));
    }
    println!(
        "{:15} {:6.2} ms per {size}px crop (supersample 2, one core)",
        "flat",
        started.elapsed().as_secs_f64() * 1e3 / n as f64
    );
    Ok(())
}
