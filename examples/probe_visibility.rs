//! Which held-out realistic crops the network misses: the set `alignist-train eval --fresh
//! --realistic` evaluates (same seed: 2⁴⁰ + 1, held-out split, exact boxes), split per SYMSOL
//! shape into thirds by three properties of the crop, each third evaluated as eval does (LL,
//! AR@30, confidently wrong):
//! - the visible fraction (the share of the object's pixels not hidden by another object or cut
//!   by the frame's edge);
//! - the object's shading contrast: the standard deviation of the luma over the object's pixels
//!   (a tetrahedron whose faces have nearly one shade shows only its outline);
//! - the outline contrast: the object's mean luma against the rest of the crop's.
//!
//! `cargo run --release --example probe_visibility [BUNDLE] [IMAGES_PER_OBJECT] [LEVEL]`
use alignist::bundle::model::ModelBundle;
use alignist::data::realism::{Realism, RealisticCrop};
use alignist::train::data::{BundleRenders, EVAL_SEED};
use alignist::train::eval::{EvalImage, evaluate};

/// Luma of every crop pixel, and whether most of its supersampled pixels are the object's.
fn luma_and_mask(crop: &RealisticCrop, size: usize) -> Vec<(f64, bool)> {
    let ss = crop.render.width as usize / size;
    (0..size * size)
        .map(|p| {
            let (x, y) = (p % size, p / size);
            let seen = (0..ss * ss)
                .filter(|q| {
                    let (bx, by) = (x * ss + q % ss, y * ss + q / ss);
                    crop.render.mask[by * crop.render.width as usize + bx]
                })
                .count();
            let rgb = &crop.rgb[3 * p..3 * p + 3];
            let luma = 0.299 * rgb[0] as f64 + 0.587 * rgb[1] as f64 + 0.114 * rgb[2] as f64;
            (luma, 2 * seen > ss * ss)
        })
        .collect()
}

fn mean_and_std(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let v: Vec<f64> = values.collect();
    let n = v.len().max(1) as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// The crop's three properties: visible fraction, shading contrast, outline contrast.
fn properties(crop: &RealisticCrop, size: usize) -> [f64; 3] {
    let pixels = luma_and_mask(crop, size);
    let (inside, shading) = mean_and_std(pixels.iter().filter(|p| p.1).map(|p| p.0));
    let (outside, _) = mean_and_std(pixels.iter().filter(|p| !p.1).map(|p| p.0));
    [crop.visible_fraction, shading, (inside - outside).abs()]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = std::path::PathBuf::from(args.get(1).map_or("models/symsol1", |s| s.as_str()));
    let per_object: usize = args.get(2).map_or(Ok(50), |s| s.parse())?;
    let level: u8 = args.get(3).map_or(Ok(3), |s| s.parse())?;
    let bundle = ModelBundle::load(&path)?;
    let config = &bundle.manifest.network;
    let size = config.image_size as usize;
    let renders = BundleRenders::of(&bundle, 2);
    let crops = renders.fresh.realistic_eval_crops(
        config.image_size,
        per_object,
        EVAL_SEED + 1,
        Realism::HELD_OUT,
    );
    println!(
        "{per_object} held-out realistic crops per object, level {level}, {}; per shape, thirds \
         by each property (low / middle / high): property range, LL, AR@30, wrong",
        path.display()
    );
    let names = ["visible fraction", "shading contrast", "outline contrast"];
    for (object, name) in renders.names.iter().enumerate() {
        let mut mine: Vec<(EvalImage, [f64; 3])> = crops
            .iter()
            .filter(|(i, _)| *i == object)
            .map(|(_, crop)| {
                let group = &renders.symmetries[object];
                let image = EvalImage::labelled(name, crop.rgb.clone(), &crop.r_virtual, group);
                (image, properties(crop, size))
            })
            .collect();
        println!("  {name}");
        for (k, property) in names.iter().enumerate() {
            mine.sort_by(|a, b| a.1[k].total_cmp(&b.1[k]));
            let third = mine.len().div_ceil(3);
            let mut row = format!("    {property:17}");
            for part in mine.chunks(third) {
                let images: Vec<EvalImage> = part.iter().map(|(im, _)| im.clone()).collect();
                let report = evaluate(&bundle.network, config, &images, level, |_| {})?;
                let o = &report.overall;
                row += &format!(
                    " | {:.2}–{:.2}: {:5.2} {:.2} {:3.0} %",
                    part[0].1[k],
                    part[part.len() - 1].1[k],
                    o.log_likelihood,
                    o.accuracy_at[0].1,
                    100.0 * o.confidently_wrong
                );
            }
            println!("{row}");
        }
    }
    Ok(())
}
