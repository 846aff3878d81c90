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

/// An MLP: `hidden_layers` ReLU layers of width `hidden`, then a linear output layer.
/// Parameters `{vb}.layers.{i}.weight` [out, in] and `.bias` [out], i = 0 … hidden_layers
/// (the output layer may go without a bias, see [`Mlp::without_output_bias`]).
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
        vb: VarBuilder,
    ) -> Result<Mlp> {
        Self::build(input, hidden, hidden_layers, output, true, vb)
    }

    /// As `new`, with no bias on the output layer: for scores that feed a softmax, where a
    /// constant added to every score changes nothing and so could never be learned.
    pub fn without_output_bias(
        input: usize,
        hidden: usize,
        hidden_layers: usize,
        output: usize,
        vb: VarBuilder,
    ) -> Result<Mlp> {
        Self::build(input, hidden, hidden_layers, output, false, vb)
    }

    /// As `new`, with the output layer's weights drawn with standard deviation `output_std`
    /// (biases zero): for outputs that must start near zero, such as ordering values, so an
    /// untrained compositor blends slots softly and every slot receives gradient.
    pub fn with_small_output(
        input: usize,
        hidden: usize,
        hidden_layers: usize,
        output: usize,
        output_std: f64,
        vb: VarBuilder,
    ) -> Result<Mlp> {
        let mut layers = Vec::with_capacity(hidden_layers + 1);
        let mut width = input;
        for i in 0..hidden_layers {
            layers.push(linear(width, hidden, vb.pp(format!("layers.{i}")))?);
            width = hidden;
        }
        let vb_out = vb.pp(format!("layers.{hidden_layers}"));
        let weight = vb_out.get_with_hints(
            (output, width),
            "weight",
            candle_nn::Init::Randn {
                mean: 0.0,
                stdev: output_std,
            },
        )?;
        let bias = vb_out.get_with_hints(output, "bias", candle_nn::Init::Const(0.0))?;
        layers.push(Linear::new(weight, Some(bias)));
        Ok(Mlp { layers })
    }

    fn build(
        input: usize,
        hidden: usize,
        hidden_layers: usize,
        output: usize,
        output_bias: bool,
        vb: VarBuilder,
    ) -> Result<Mlp> {
        let mut layers = Vec::with_capacity(hidden_layers + 1);
        let mut width = input;
        for i in 0..=hidden_layers {
            let out = if i == hidden_layers { output } else { hidden };
            let vb_i = vb.pp(format!("layers.{i}"));
            layers.push(if i == hidden_layers && !output_bias {
                candle_nn::linear_no_bias(width, out, vb_i)?
            } else {
                linear(width, out, vb_i)?
            });
            width = out;
        }
        Ok(Mlp { layers })
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
