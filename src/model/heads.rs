//! Heads on a light field's ray feature (COLF supplement §1.2): colour (3, sigmoid, in [0, 1])
//! and the ordering value o (1, linear, in units of `scene_scale`); with `Config::shadow_head`
//! also a shadow density σ (see [`ShadowHead`]). Shared by the background and the foreground
//! slots. Tensor names: `heads.color.layers.{i}.{weight,bias}`,
//! `heads.ordering.layers.{i}.{weight,bias}`, i = 0 … head_hidden_layers;
//! `heads.shadow.{weight [1, F], bias [1], gate [1]}`.

use super::config::Config;
use super::layers::Mlp;
use candle_core::{Module, Result, Tensor};
use candle_nn::{Init, Linear, VarBuilder};

/// Bias of the shadow logit at initialisation: sigmoid(−4) ≈ 0.018, so a new slot's shadow
/// starts faint everywhere and grows only where the colour loss asks for it.
pub const SHADOW_BIAS_INIT: f64 = -4.0;

/// The gate's gain: σ uses `SHADOW_GATE_GAIN`·gate, so Adam, which moves a parameter by about
/// the learning rate a step whatever its gradient's scale, opens shadows within ~10³ steps at
/// 10⁻⁴ (at gain 1 the gate had moved 0.0002 after 30 such steps).
pub const SHADOW_GATE_GAIN: f64 = 10.0;

/// How much a foreground slot darkens the background on a ray: σ = g · gate · sigmoid(w·f + b)
/// (g = [`SHADOW_GATE_GAIN`]),
/// f the slot's ray feature. The compositor multiplies the background's colour by
/// exp(−Σ σ) over the foreground slots (`ColfModel::decode`).
///
/// Why the gate: it starts at 0, so adding the head to a trained model changes nothing it
/// computes (`grow.rs`), yet the gate receives a gradient from the first step (wherever the
/// background's colour is wrong), and w, b follow once it is non-zero.
#[derive(Clone, Debug)]
pub struct ShadowHead {
    logit: Linear,
    gate: Tensor,
}

impl ShadowHead {
    fn new(features: usize, vb: VarBuilder) -> Result<ShadowHead> {
        let a = 1.0 / (features as f64).sqrt();
        let weight = vb.get_with_hints((1, features), "weight", Init::Uniform { lo: -a, up: a })?;
        let bias = vb.get_with_hints(1, "bias", Init::Const(SHADOW_BIAS_INIT))?;
        let gate = vb.get_with_hints(1, "gate", Init::Const(0.0))?;
        Ok(ShadowHead {
            logit: Linear::new(weight, Some(bias)),
            gate,
        })
    }

    /// features [.., F] → σ [.., 1].
    pub fn forward(&self, features: &Tensor) -> Result<Tensor> {
        let gate = (&self.gate * SHADOW_GATE_GAIN)?;
        candle_nn::ops::sigmoid(&self.logit.forward(features)?)?.broadcast_mul(&gate)
    }
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
            color: Mlp::new(f, h, n, 3, vb.pp("color"))?,
            // Ordering values start near zero (std 1e-3 of the output layer): with the
            // compositor's depth prior, untrained heads with O(10) orderings made the weights
            // one-hot from the first step, and slots behind never received gradient.
            ordering: Mlp::with_small_output(f, h, n, 1, 1e-3, vb.pp("ordering"))?,
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

    /// features [.., F] → shadow density σ [.., 1], when the model has a shadow head.
    pub fn shadow(&self, features: &Tensor) -> Result<Option<Tensor>> {
        self.shadow
            .as_ref()
            .map(|s| s.forward(features))
            .transpose()
    }
}
