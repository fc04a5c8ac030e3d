//! Probe: does the network learn image-dependent distributions in a few hundred steps?
//! Trains the IPDF objective on cube renders and prints held-out metrics at level 2.
use std::ops::ControlFlow;

use alignist::bundle::experts::{bake_experts, key_siren_config};
use alignist::cad::Shape;
use alignist::encoding::RotationEncoding;
use alignist::experts::SirenConfig;
use alignist::experts::energy::EnergyParams;
use alignist::net::ResNetLayout;
use alignist::so3::haar_rotations;
use alignist::train::eval::{EvalImage, evaluate};
use alignist::train::{Method, NetworkConfig, TrainConfig, TrainingImage, TrainingSet, train};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn main() {
    let steps: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(300);
    let lr: f64 = std::env::args()
        .nth(2)
        .and_then(|s| s.parse().ok())
        .unwrap_or(1e-3);
    let device = alignist::backend::device();
    let mesh = Shape::Cube.mesh();
    // With a third argument (an expert set folder), train the Alignist objective instead.
    let experts = std::env::args().nth(3);
    // A fourth argument scales both λ (softer targets for training when below 1).
    let lambda_scale: f64 = std::env::args()
        .nth(4)
        .and_then(|s| s.parse().ok())
        .unwrap_or(1.0);
    let (baked, modes) = match &experts {
        Some(dir) => {
            let set =
                alignist::bundle::experts::ExpertSet::load(std::path::Path::new(dir)).unwrap();
            let mut b = set.bake();
            let modes = vec![set.mode_table(&b).unwrap()];
            b.params.lambda_sdf *= lambda_scale;
            b.params.lambda_se *= lambda_scale;
            (b, modes)
        }
        None => (
            bake_experts(
                &SirenConfig::new(3, 8, 1, 1).init(&device),
                &key_siren_config().init(&device),
                8,
                1.05,
                EnergyParams::default(),
                &device,
            ),
            Vec::new(),
        ),
    };
    let size = 32;
    let camera = alignist::cad::Camera::square(size);
    let render_at = |r| {
        alignist::cad::render(
            &mesh,
            &camera,
            &alignist::data::symsol_pose(r),
            &alignist::cad::RenderOptions::default(),
        )
        .rgb
    };
    let images = haar_rotations(&mut ChaCha8Rng::seed_from_u64(21), 1000)
        .into_iter()
        .enumerate()
        .map(|(i, r)| TrainingImage {
            object: 0,
            rgb: render_at(r),
            rotation: r,
            visible: alignist::experts::select::visible_points_at(&mesh, &r, i as u64),
        })
        .collect();
    let set = TrainingSet {
        objects: vec![baked],
        modes,
        images,
        fresh: None,
    };
    let cfg = TrainConfig {
        network: NetworkConfig::new(ResNetLayout::Tiny, RotationEncoding::Cube)
            .with_image_size(size),
        method: if experts.is_some() {
            Method::Alignist {
                loss: alignist::train::MeasureLoss::Gkl,
                sampling: alignist::train::SamplingStrategy::mode_focused(256),
            }
        } else {
            Method::Ipdf
        },
        steps,
        batch: 16,
        k: 256,
        lr,
        warmup: 10,
        seed: 1,
        checkpoint_every: 1000000,
    };
    let t = std::time::Instant::now();
    let (network, report) = train(&cfg, &set, None, false, |s, _, l| {
        if s % 50 == 0 {
            eprintln!("step {s} loss {l:.3} ({:.1} s)", t.elapsed().as_secs_f64());
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    let held: Vec<EvalImage> = haar_rotations(&mut ChaCha8Rng::seed_from_u64(77), 20)
        .into_iter()
        .map(|r| EvalImage {
            object: "cube".into(),
            rgb: render_at(r),
            equivalents: alignist::so3::equivalents(&r, &Shape::Cube.symmetries()),
        })
        .collect();
    let e = evaluate(&network, &cfg.network, &held, 2, |_| {}).unwrap();
    println!(
        "lambda x{lambda_scale}, {steps} steps lr {lr}: final loss {:.3}, held-out {:?}",
        report.final_loss, e.overall
    );
}
