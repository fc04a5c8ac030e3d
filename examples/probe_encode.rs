//! Time of the cube encoding against the head's rotation projection and scoring, for 4 096
//! rotations (one refined level of a keep-512 search).
//! `cargo run --release --example probe_encode`
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let path = std::path::Path::new("models/symsol1");
    let bundle = alignist::bundle::model::ModelBundle::load(path)?;
    let head = alignist::net::FusedHead::new(&bundle.network.head);
    let grid = alignist::so3::GridLevel::new(4)?;
    let time = |what: &str, f: &mut dyn FnMut()| {
        f();
        let t = Instant::now();
        for _ in 0..20 {
            f();
        }
        println!("{what}: {:.2} ms", t.elapsed().as_secs_f64() * 1e3 / 20.0);
    };
    let cells: Vec<u64> = (0..4096u64).map(|i| i * 71).collect();
    let mut mats = Vec::new();
    time("rotations of 4096 cells", &mut || {
        mats = cells
            .iter()
            .map(|&c| {
                let r = grid.rotation(c);
                std::array::from_fn(|j| r.matrix()[(j / 3, j % 3)] as f32)
            })
            .collect();
    });
    let encoding = bundle.manifest.network.encoding;
    let mut enc = Vec::new();
    time("encode", &mut || enc = encoding.encode(&mats));
    let mut projected = Vec::new();
    time("project", &mut || projected = head.project_rotations(&enc));
    let image = head.image_term(&vec![0.5; head.image_dim()]);
    for precision in [
        alignist::net::Precision::F32,
        alignist::net::Precision::Bf16,
    ] {
        time(&format!("scores {precision}"), &mut || {
            head.scores_in(
                precision,
                &image,
                alignist::net::Rows::Projected(&projected),
            );
        });
    }
    for precision in [
        alignist::net::Precision::F32,
        alignist::net::Precision::Bf16,
    ] {
        time(&format!("scores of encodings {precision}"), &mut || {
            head.scores_in(precision, &image, alignist::net::Rows::Encoded(&enc));
        });
    }
    Ok(())
}
