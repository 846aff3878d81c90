//! Heads on a light field's ray feature (COLF supplement §1.2): colour (3, sigmoid, in [0, 1])
//! and the ordering value o (1, linear, in units of `scene_scale`). Shared by the background and
//! the foreground slots. Tensor names: `heads.color.layers.{i}.{weight,bias}`,
//! `heads.ordering.layers.{i}.{weight,bias}`, i = 0 … head_hidden_layers.

use super::config::Config;
use super::layers::Mlp;
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

#[derive(Clone, Debug)]
pub struct Heads {
    color: Mlp,
    ordering: Mlp,
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
        })
    }

    /// features [.., F] → (colour [.., 3] in [0, 1], ordering [.., 1]).
    pub fn forward(&self, features: &Tensor) -> Result<(Tensor, Tensor)> {
        let color = candle_nn::ops::sigmoid(&self.color.forward(features)?)?;
        let ordering = self.ordering.forward(features)?;
        Ok((color, ordering))
    }
}
