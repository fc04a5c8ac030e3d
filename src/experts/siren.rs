//! SIREN MLP (Sitzmann et al. 2020): `sin(ω₀·(W x + b))` hidden layers and a linear output,
//! with SIREN's initialisation. Used for the SDF expert (3 → 1) and the surface keys (3 → 12).

use burn::config::Config;
use burn::module::Module;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::{Device, Tensor};

/// Shape of a SIREN.
#[derive(Config, Debug)]
pub struct SirenConfig {
    /// Input size (3 for points).
    pub d_input: usize,
    /// Width of the hidden sine layers.
    pub hidden: usize,
    /// Number of hidden sine layers.
    pub layers: usize,
    /// Output size.
    pub d_output: usize,
    /// Frequency of the sines, ω₀ (SIREN: 30).
    #[config(default = 30.0)]
    pub omega0: f64,
}

/// A SIREN network.
#[derive(Module, Debug)]
pub struct Siren {
    hidden: Vec<Linear>,
    output: Linear,
    #[module(skip)]
    omega0: f64,
}

impl SirenConfig {
    /// SIREN initialisation: the first layer `U(−1/d_in, 1/d_in)`, the others
    /// `U(−√(6/d_in)/ω₀, √(6/d_in)/ω₀)` (weights and biases).
    pub fn init(&self, device: &Device) -> Siren {
        let mut hidden = Vec::with_capacity(self.layers);
        let mut d_in = self.d_input;
        for k in 0..self.layers {
            let bound = if k == 0 {
                1.0 / d_in as f64
            } else {
                (6.0 / d_in as f64).sqrt() / self.omega0
            };
            hidden.push(
                LinearConfig::new(d_in, self.hidden)
                    .with_initializer(Initializer::Uniform {
                        min: -bound,
                        max: bound,
                    })
                    .init(device),
            );
            d_in = self.hidden;
        }
        let bound = (6.0 / d_in as f64).sqrt() / self.omega0;
        let output = LinearConfig::new(d_in, self.d_output)
            .with_initializer(Initializer::Uniform {
                min: -bound,
                max: bound,
            })
            .init(device);
        Siren {
            hidden,
            output,
            omega0: self.omega0,
        }
    }
}

impl Siren {
    /// `[n, d_input] → [n, d_output]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let mut h = x;
        for layer in &self.hidden {
            h = layer.forward(h).mul_scalar(self.omega0).sin();
        }
        self.output.forward(h)
    }
}
