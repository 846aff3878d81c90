//! The light-field compositor (COLF §3.2): per ray, the S slots' ordering values become
//! visibility scores v_i = V(o_i, o_min − o_i), softmax-normalised into the weights that blend
//! the slots' colours; the weights are the soft segmentation.
//!
//! **Composition across frames.** A slot's light field sees only the line of the ray (Plücker
//! coordinates in its own frame), so its ordering value o_i can only be measured along the line
//! from the point closest to the slot's frame origin. Slots that were moved or merged live in
//! different frames, so raw ordering values are not comparable. Before compositing, each is
//! shifted by where that closest point lies on the query ray:
//! `o_i_world = scene_scale · o_i + dot(t_i − ray_origin, d)` (t_i = translation of
//! `slot_to_world`, 0 for the background; computed in `rays.rs`). With a common frame (all slots
//! from one image) the shift is the same for all foreground slots and changes nothing (the paper
//! noted that such a shift preserves differences); with moved slots it is what puts them in
//! front-to-back order.
//!
//! **Bounded inputs.** o_i_world can be ~10⁴ (a camera or slot far away). V never sees it: its
//! inputs are the slot's own ordering value o_i (a function of bounded ray coordinates) and the
//! gap g_i = (o_i_world − min_j o_j_world)/scene_scale ≥ 0 squashed to g_i/√(1 + g_i²) ∈ [0, 1).
//! The score also has a monotone prior term −exp(`gap_log_slope`)·g_i (learned, slope > 0): a
//! slot far behind the front one is pushed out however V was initialised, so front-to-back order
//! holds from the first step, and V learns the near-tie kernel. The softmax subtracts the per-ray
//! maximum, so any finite scores give finite weights summing to 1.
//!
//! Tensor names: `compositor.v.layers.{i}.{weight,bias}` (no bias on the output layer: a
//! constant added to every score is invisible to the softmax), `compositor.gap_log_slope` [1].

use super::config::Config;
use super::layers::{Mlp, OutputLayer};
use candle_core::{Module, Result, Tensor, D};
use candle_nn::{Init, VarBuilder};

#[derive(Clone, Debug)]
pub struct Compositor {
    v: Mlp,
    gap_log_slope: Tensor,
    scene_scale: f64,
}

/// Compositor outputs, all [B, R, S].
#[derive(Clone, Debug)]
pub struct Composite {
    /// Softmax weights over the slots (background first).
    pub weights: Tensor,
    /// Their logarithms, from a log-softmax (finite gradients even where a weight underflows:
    /// training losses on weights must use these, not `weights.log()`).
    pub log_weights: Tensor,
    /// World-comparable ordering values minus the per-ray base shift (world units).
    pub ordering: Tensor,
}

impl Compositor {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Compositor> {
        Ok(Compositor {
            v: Mlp::new(
                2,
                cfg.compositor_hidden,
                cfg.compositor_hidden_layers,
                1,
                OutputLayer::NoBias,
                vb.pp("v"),
            )?,
            // Initial slope 1 per scene_scale of depth gap: soft enough that every slot gets
            // gradient at the start of training (a slope of 10 made the weights one-hot), still
            // strictly front-to-back; training steepens it as the orderings become reliable.
            gap_log_slope: vb.get_with_hints(1, "gap_log_slope", Init::Const(0.0))?,
            scene_scale: cfg.scene_scale,
        })
    }

    /// The parameters in the order the decode kernel packs them (`decode_kernel::SharedLayout`):
    /// V's layers (weight, then bias where there is one), then `gap_log_slope`.
    pub fn kernel_parameters(&self) -> Vec<Tensor> {
        let mut out = Vec::new();
        for layer in self.v.linears() {
            out.push(layer.weight().clone());
            out.extend(layer.bias().cloned());
        }
        out.push(self.gap_log_slope.clone());
        out
    }

    /// ordering [B, R, S] (the heads' values), shift [B, R, S] (world units, from `RayBatch`).
    pub fn forward(&self, ordering: &Tensor, shift: &Tensor) -> Result<Composite> {
        self.forward_present(ordering, shift, None)
    }

    /// [`Compositor::forward`] with some slots absent from some rays: `present` [B, R, S]
    /// (u8, 1 = present; the background present on every ray). An absent slot has ordering
    /// +∞, weight 0 and log-weight −∞, does not count for the front, and passes no gradient.
    pub fn forward_present(
        &self,
        ordering: &Tensor,
        shift: &Tensor,
        present: Option<&Tensor>,
    ) -> Result<Composite> {
        let mut world = (ordering * self.scene_scale)?.add(shift)?;
        let absent_as = |t: &Tensor, v: f64| match present {
            Some(p) => p.where_cond(t, &Tensor::full(v as f32, t.shape(), t.device())?),
            None => Ok(t.clone()),
        };
        world = absent_as(&world, f64::INFINITY)?;
        let front = world.min_keepdim(D::Minus1)?;
        let gap = absent_as(&world.broadcast_sub(&front)?, 0.0)?;
        let gap = (gap / self.scene_scale)?; // ≥ 0
        let squashed = gap.broadcast_div(&(gap.sqr()? + 1.0)?.sqrt()?)?;
        let inputs = Tensor::stack(&[ordering, &squashed.neg()?], D::Minus1)?; // [B, R, S, 2]
        let learned = self.v.forward(&inputs)?.squeeze(D::Minus1)?;
        let prior = gap.broadcast_mul(&self.gap_log_slope.exp()?)?;
        let scores = absent_as(&(learned - prior)?, f64::NEG_INFINITY)?;
        Ok(Composite {
            weights: candle_nn::ops::softmax(&scores, D::Minus1)?,
            // An absent slot's −∞ is a constant: a loss on it reaches no present slot.
            log_weights: absent_as(
                &candle_nn::ops::log_softmax(&scores, D::Minus1)?,
                f64::NEG_INFINITY,
            )?,
            ordering: world,
        })
    }
}
