//! The per-slot light-field networks Φ(r; z), evaluated for all slots at once.
//!
//! A light field is an MLP whose weights come from a hypernetwork (see `hypernet.rs`). All S
//! slots' MLPs run as batched matmuls x [S, R, in] · W [S, in, out] — as fast as one big matmul
//! on this CPU, where a per-slot loop measured 2–3× slower. The generated weights are
//! computed once per slot ([`SlotWeights`]) and reused for any number of rays, views and chunks;
//! the authors' code re-ran the hypernetworks for every (slot, view) pair.

use super::fused::{dense, Activation};
use super::hypernet::GeneratedLayer;
use candle_core::{Result, Tensor};

/// The generated weights of S light fields, layer by layer (input layer first).
#[derive(Clone, Debug)]
pub struct SlotWeights {
    pub layers: Vec<GeneratedLayer>,
}

impl SlotWeights {
    /// Number of light fields S.
    pub fn num_fields(&self) -> Result<usize> {
        self.layers[0].weight.dim(0)
    }

    /// Lays out per-scene fields as [scene 0: bg, fg 0 … fg K−1, scene 1: …]: `bg` holds B
    /// fields, `fg` B·K (scene-major), K may be 0.
    pub fn join_scenes(
        bg: &SlotWeights,
        fg: Option<&SlotWeights>,
        b: usize,
        k: usize,
    ) -> Result<SlotWeights> {
        let fg = match fg {
            Some(fg) if k > 0 => fg,
            _ => return Ok(bg.clone()),
        };
        let layers = bg
            .layers
            .iter()
            .zip(&fg.layers)
            .map(|(lb, lf)| {
                let join = |tb: &Tensor, tf: &Tensor| -> Result<Tensor> {
                    let (_, r, c) = tb.dims3()?;
                    Tensor::cat(&[&tb.reshape((b, 1, r, c))?, &tf.reshape((b, k, r, c))?], 1)?
                        .reshape((b * (1 + k), r, c))
                };
                Ok(GeneratedLayer {
                    weight: join(&lb.weight, &lf.weight)?,
                    bias: join(&lb.bias, &lf.bias)?,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(SlotWeights { layers })
    }

    /// Evaluates the S light fields: rays [S, R, in] (slot s's rays in its own frame) →
    /// ray features [S, R, F]. ReLU between layers; the feature layer is linear.
    pub fn forward(&self, rays: &Tensor) -> Result<Tensor> {
        let mut x = rays.clone();
        for (i, layer) in self.layers.iter().enumerate() {
            let act = if i + 1 < self.layers.len() {
                Activation::Relu
            } else {
                Activation::Identity
            };
            x = dense(&x, &layer.weight, &layer.bias, act)?;
        }
        Ok(x)
    }
}
