//! Small building blocks shared by the modules, written only with ops that have a backward
//! (candle 0.11's fused layer norm records no gradient, so norms here are composed of plain ops).

use super::fused::{dense, Activation};
use candle_core::{Module, Result, Tensor};
use candle_nn::{linear, Linear, VarBuilder};

/// Layer normalisation over the last axis with a learned scale and shift, built from plain ops
/// (`candle_nn::ops::layer_norm_slow`) so gradients reach the input, `weight` and `bias`.
#[derive(Clone, Debug)]
pub struct LayerNormSlow {
    weight: Tensor,
    bias: Tensor,
}

impl LayerNormSlow {
    /// Parameters `{vb}.weight` (ones) and `{vb}.bias` (zeros), both [dim].
    pub fn new(dim: usize, vb: VarBuilder) -> Result<LayerNormSlow> {
        Ok(LayerNormSlow {
            weight: vb.get_with_hints(dim, "weight", candle_nn::init::ONE)?,
            bias: vb.get_with_hints(dim, "bias", candle_nn::init::ZERO)?,
        })
    }
}

impl Module for LayerNormSlow {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        candle_nn::ops::layer_norm_slow(x, &self.weight, &self.bias, 1e-5)
    }
}

/// How an [`Mlp`]'s output layer starts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum OutputLayer {
    /// A linear layer with a bias, initialised like the hidden layers.
    Plain,
    /// No bias: for scores that feed a softmax, where a constant added to every score changes
    /// nothing and so could never be learned.
    NoBias,
    /// Weights drawn with this standard deviation, biases zero: for outputs that must start
    /// near zero, such as ordering values, so an untrained compositor blends slots softly and
    /// every slot receives gradient.
    Small(f64),
}

/// An MLP: `hidden_layers` ReLU layers of width `hidden`, then a linear output layer.
/// Parameters `{vb}.layers.{i}.weight` [out, in] and `.bias` [out], i = 0 … hidden_layers
/// (the output layer may go without a bias, see [`OutputLayer`]).
#[derive(Clone, Debug)]
pub struct Mlp {
    layers: Vec<Linear>,
}

impl Mlp {
    pub fn new(
        input: usize,
        hidden: usize,
        hidden_layers: usize,
        output: usize,
        output_layer: OutputLayer,
        vb: VarBuilder,
    ) -> Result<Mlp> {
        let mut layers = Vec::with_capacity(hidden_layers + 1);
        let mut width = input;
        for i in 0..hidden_layers {
            layers.push(linear(width, hidden, vb.pp(format!("layers.{i}")))?);
            width = hidden;
        }
        let vb_out = vb.pp(format!("layers.{hidden_layers}"));
        layers.push(match output_layer {
            OutputLayer::Plain => linear(width, output, vb_out)?,
            OutputLayer::NoBias => candle_nn::linear_no_bias(width, output, vb_out)?,
            OutputLayer::Small(stdev) => {
                let weight = vb_out.get_with_hints(
                    (output, width),
                    "weight",
                    candle_nn::Init::Randn { mean: 0.0, stdev },
                )?;
                let bias = vb_out.get_with_hints(output, "bias", candle_nn::Init::Const(0.0))?;
                Linear::new(weight, Some(bias))
            }
        });
        Ok(Mlp { layers })
    }

    /// The layers, input layer first.
    pub fn linears(&self) -> &[Linear] {
        &self.layers
    }
}

impl Module for Mlp {
    /// x [.., in] → [.., out]; leading axes are flattened so every layer is one plain 2-D
    /// matmul (candle's `Linear` on 3-D input takes a slower broadcast path), run as a fused
    /// dense layer (`fused.rs`: bias and ReLU in the same op, fast backward).
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let inner = dims[dims.len() - 1];
        let rows = x.elem_count() / inner.max(1);
        let mut x = x.reshape((rows, inner))?;
        for (i, layer) in self.layers.iter().enumerate() {
            let act = if i + 1 < self.layers.len() {
                Activation::Relu
            } else {
                Activation::Identity
            };
            x = match layer.bias() {
                Some(bias) => dense(&x, &layer.weight().t()?, bias, act)?,
                None => {
                    let y = layer.forward(&x)?;
                    if act == Activation::Relu {
                        y.relu()?
                    } else {
                        y
                    }
                }
            };
        }
        let mut out_dims = dims;
        let last = out_dims.len() - 1;
        out_dims[last] = x.dim(1)?;
        x.reshape(out_dims)
    }
}
