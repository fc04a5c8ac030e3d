//! Which factor of the realistic crops a model misses: the held-out set `alignist-train eval
//! --fresh --realistic` evaluates (same seed: `EVAL_SEED` + 1, held-out split, exact boxes),
//! made again with one factor at a time held at a neutral value (`Realism::neutral`: a matte
//! grey material, one white light, a black background, no camera effects; `clutter` 0: no other
//! objects; `truncation` 0: never cut by the frame), then with all of them. Every crop keeps its
//! pose in every row (each factor but the camera, the crop's last draw, is still drawn, then
//! replaced), so the rows are paired: a row far above the first names a variation the model has
//! not learned.
//! `cargo run --release --example probe_factors [BUNDLE] [IMAGES_PER_OBJECT] [LEVEL]`
use alignist::bundle::model::ModelBundle;
use alignist::data::realism::{Neutral, Realism};
use alignist::train::data::{BundleRenders, EVAL_SEED};
use alignist::train::eval::evaluate;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = std::path::PathBuf::from(args.get(1).map_or("models/symsol1", |s| s.as_str()));
    let per_object: usize = args.get(2).map_or(Ok(100), |s| s.parse())?;
    let level: u8 = args.get(3).map_or(Ok(3), |s| s.parse())?;
    let bundle = ModelBundle::load(&path)?;
    let config = &bundle.manifest.network;
    let renders = BundleRenders::of(&bundle, 2);
    let rows = rows();
    println!(
        "{per_object} held-out realistic crops per object, level {level}, {}: LL, AR@30 (argmax), \
         share below uniform, half-turn share; per object",
        path.display()
    );
    for (label, realism) in rows {
        let images =
            renders.realistic_eval_images(config.image_size, per_object, EVAL_SEED + 1, realism);
        let report = evaluate(&bundle.network, config, &images, level, |_| {})?;
        let mut row = format!("  {label:36}");
        for (object, o) in &report.per_object {
            row += &format!(
                " | {object}: {:5.2} {:.2} {:3.0} % {:3.0} %",
                o.log_likelihood,
                o.accuracy_at[0].1,
                100.0 * o.confidently_wrong,
                100.0 * o.half_turn_wrong
            );
        }
        println!("{row}");
    }
    Ok(())
}

/// The held-out realism, then with one factor neutral at a time, then all of them.
fn rows() -> [(&'static str, Realism); 8] {
    let all = Neutral {
        material: true,
        lighting: true,
        background: true,
        camera: true,
    };
    let base = Realism::HELD_OUT;
    [
        ("as evaluated (every factor varies)", base),
        (
            "material neutral",
            Realism {
                neutral: Neutral {
                    material: true,
                    ..Neutral::NONE
                },
                ..base
            },
        ),
        (
            "lighting neutral",
            Realism {
                neutral: Neutral {
                    lighting: true,
                    ..Neutral::NONE
                },
                ..base
            },
        ),
        (
            "background black",
            Realism {
                neutral: Neutral {
                    background: true,
                    ..Neutral::NONE
                },
                ..base
            },
        ),
        (
            "camera neutral",
            Realism {
                neutral: Neutral {
                    camera: true,
                    ..Neutral::NONE
                },
                ..base
            },
        ),
        (
            "no other objects",
            Realism {
                clutter: 0.0,
                ..base
            },
        ),
        (
            "never cut by the frame",
            Realism {
                truncation: 0.0,
                ..base
            },
        ),
        (
            "all of these",
            Realism {
                neutral: all,
                clutter: 0.0,
                truncation: 0.0,
                ..base
            },
        ),
    ]
}
