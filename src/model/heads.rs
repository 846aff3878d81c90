//! Heads on a light field's ray feature (COLF supplement §1.2): colour (3, sigmoid, in [0, 1])
//! and the ordering value o (1, linear, in units of `scene_scale`); with `Config::shadow_head`
//! also a shadow density σ (see [`ShadowHead`]). Shared by the background and the foreground
//! slots. Tensor names: `heads.color.layers.{i}.{weight,bias}`,
//! `heads.ordering.layers.{i}.{weight,bias}`, i = 0 … head_hidden_layers;
//! `heads.shadow.{weight [1, F], bias [1]}`.

use super::config::Config;
use super::layers::{Mlp, OutputLayer};
use candle_core::{Module, Result, Tensor};
use candle_nn::{Init, Linear, VarBuilder};

/// The shadow logit is `SHADOW_LOGIT_GAIN`·(w·f + b): Adam moves each parameter by about the
/// learning rate a step whatever its gradient's scale, so the gain is the head's learning rate
/// relative to the rest of the model (at gain 1 and 10⁻⁴, b had moved 0.004 in 750 steps).
pub const SHADOW_LOGIT_GAIN: f64 = 10.0;

/// b at initialisation (with w = 0): every slot starts with σ = softplus(−8) ≈ 3.4·10⁻⁴ on every
/// ray, so adding the head to a trained model darkens its background by 0.03 % per slot, and w
/// learns where the shadows are from there.
pub const SHADOW_BIAS_INIT: f64 = -8.0 / SHADOW_LOGIT_GAIN;

/// How much a foreground slot darkens the background on a ray: σ = softplus(g·(w·f + b)) ≥ 0, f
/// the slot's ray feature, g = [`SHADOW_LOGIT_GAIN`]. The compositor multiplies the background's colour by exp(−Σ σ) over the
/// foreground slots (`ColfNet::decode`).
///
/// Why softplus and this initialisation: σ must be ≥ 0 and start near 0, and every parameter
/// must receive a consistent gradient from the first step. A gate initialised at 0 (σ = gate ·
/// sigmoid(…)) kept the function exactly but did not train: the gradient of w is proportional
/// to the gate, and the gate's own gradient (darker in shadows, brighter on lit floor) averaged
/// out, so after 1,000 steps it was still 3·10⁻⁵. With w = 0 and b = −8 the gradient of w is
/// the correlation of the ray features with where the background is too bright.
#[derive(Clone, Debug)]
pub struct ShadowHead {
    logit: Linear,
}

impl ShadowHead {
    fn new(features: usize, vb: VarBuilder) -> Result<ShadowHead> {
        let weight = vb.get_with_hints((1, features), "weight", Init::Const(0.0))?;
        let bias = vb.get_with_hints(1, "bias", Init::Const(SHADOW_BIAS_INIT))?;
        Ok(ShadowHead {
            logit: Linear::new(weight, Some(bias)),
        })
    }

    /// features [.., F] → σ [.., 1].
    pub fn forward(&self, features: &Tensor) -> Result<Tensor> {
        softplus(&(self.logit.forward(features)? * SHADOW_LOGIT_GAIN)?)
    }
}

/// softplus(x) = ln(1 + eˣ), as max(x, 0) + ln(1 + e^−|x|): no overflow for large x.
fn softplus(x: &Tensor) -> Result<Tensor> {
    x.relu()? + (x.abs()?.neg()?.exp()? + 1.0)?.log()?
}

/// σ on the host from w·f + b, the same formula as [`ShadowHead`]'s.
pub fn shadow_host(affine: f32) -> f32 {
    let x = affine * SHADOW_LOGIT_GAIN as f32;
    x.max(0.0) + (-x.abs()).exp().ln_1p()
}

#[derive(Clone, Debug)]
pub struct Heads {
    color: Mlp,
    ordering: Mlp,
    shadow: Option<ShadowHead>,
}

impl Heads {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Heads> {
        let (f, h, n) = (cfg.lfn_features, cfg.head_hidden, cfg.head_hidden_layers);
        Ok(Heads {
            color: Mlp::new(f, h, n, 3, OutputLayer::Plain, vb.pp("color"))?,
            // Ordering values start near zero (std 1e-3 of the output layer): with the
            // compositor's depth prior, untrained heads with O(10) orderings made the weights
            // one-hot from the first step, and slots behind never received gradient.
            ordering: Mlp::new(f, h, n, 1, OutputLayer::Small(1e-3), vb.pp("ordering"))?,
            shadow: if cfg.shadow_head {
                Some(ShadowHead::new(f, vb.pp("shadow"))?)
            } else {
                None
            },
        })
    }

    /// features [.., F] → (colour [.., 3] in [0, 1], ordering [.., 1]).
    pub fn forward(&self, features: &Tensor) -> Result<(Tensor, Tensor)> {
        let color = candle_nn::ops::sigmoid(&self.color.forward(features)?)?;
        let ordering = self.ordering.forward(features)?;
        Ok((color, ordering))
    }

    /// The heads' parameters in the order the decode kernel packs them
    /// (`decode_kernel::SharedLayout`): per colour layer its weight and bias, the same for the
    /// ordering head, then the shadow head's weight and bias.
    pub fn kernel_parameters(&self) -> Vec<Tensor> {
        let mut out = Vec::new();
        for mlp in [&self.color, &self.ordering] {
            for layer in mlp.linears() {
                out.push(layer.weight().clone());
                out.extend(layer.bias().cloned());
            }
        }
        if let Some(shadow) = &self.shadow {
            out.push(shadow.logit.weight().clone());
            out.extend(shadow.logit.bias().cloned());
        }
        out
    }

    /// features [.., F] → shadow density σ [.., 1], when the model has a shadow head.
    pub fn shadow(&self, features: &Tensor) -> Result<Option<Tensor>> {
        self.shadow
            .as_ref()
            .map(|s| s.forward(features))
            .transpose()
    }
}
