//! The volumetric baseline: a uORF-style decoder (Yu et al., "Unsupervised Discovery of
//! Object Radiance Fields", ICLR 2022) in place of COLF's light fields, on the same encoder and
//! slot attention, so the cost of the two ways of rendering slots can be compared in one code
//! base (`make bench`, `docs/speed.md`).
//!
//! Per slot s with latent z_s, for every sample point p along a ray (in the slot's frame for a
//! foreground slot, world space for the background, divided by `scene_scale`):
//! ```text
//! e = γ(p) = [p, sin(2^k·π·p), cos(2^k·π·p)]   k < pos_freqs            (E = 3·(1 + 2L))
//! h = ReLU(W_0·[e; z_s] + b_0), then layers_before_skip − 1 ReLU layers of width W
//! h = ReLU(W_B·[h; e; z_s] + b_B) (the skip), then layers_after_skip − 1 ReLU layers
//! σ_s = ReLU(w_σ·h + b_σ)          c_s = sigmoid(W_c2·ReLU(W_c1·h + b_c1) + b_c2)
//! ```
//! with separate weights for the background (`bg.`) and the foreground slots (`fg.`) as in uORF.
//! Slots are composed per sample by density (σ = Σ_s σ_s, c = Σ_s σ_s·c_s / σ), then alpha
//! composited along the ray over `samples` stratified midpoints t_i between `near` and `far`
//! (δ = (far − near)/N): α_i = 1 − exp(−σ_i·δ), T_i = Π_{j<i}(1 − α_j), colour = Σ_i T_i·α_i·c_i.
//! Slot s's weight (its soft segmentation) is Σ_i T_i·α_i·σ_s,i/σ_i; the transmittance left
//! after the last sample goes to the background, so the weights sum to 1. Its ordering value
//! is its expected depth Σ_i T_i·α_i·(σ_s,i/σ_i)·t_i / weight (world units from the ray origin).
//!
//! The latent enters by concatenation, as in uORF; its part of W_0 and W_B is the same for
//! every sample of a slot, so the fast renderer (`crate::render::fast`) folds W·z into a per-slot
//! bias once and runs only the E (and W + E) columns per sample — the same arithmetic, none of
//! it repeated. The candle [`Volumetric::forward`] here is the reference it is tested against.
//!
//! Tensor names (prefix `volumetric.`), W = `hidden`, E = 3·(1 + 2·`pos_freqs`), D = slot dim,
//! B = `layers_before_skip`, A = `layers_after_skip`, C = `color_hidden`:
//! - `{bg,fg}.layers.{i}.weight` / `.bias`, i = 0 … B + A − 1: layer 0 [W, E + D], layer B (the
//!   skip) [W, W + E + D], the others [W, W]; biases [W]. Input columns in the order written above.
//! - `{bg,fg}.density.weight` / `.bias`: [1, W] / [1].
//! - `{bg,fg}.color.layers.0.weight` / `.bias`: [C, W] / [C]; `.color.layers.1.*`: [3, C] / [3].

use super::config::{Config, VolumetricConfig};
use super::fused::{dense, Activation};
use anyhow::{bail, Result};
use candle_core::{Tensor, D};
use candle_nn::{linear, Linear, VarBuilder};
use glam::{DMat4, DVec3};

/// One slot kind's network (background or foreground).
#[derive(Clone, Debug)]
pub struct VolumeNet {
    /// Layers 0 … B + A − 1 (layer 0 and layer B take the concatenated inputs).
    pub layers: Vec<Linear>,
    pub density: Linear,
    pub color_hidden: Linear,
    pub color_out: Linear,
}

/// The volumetric decoder: background and foreground networks.
#[derive(Clone, Debug)]
pub struct Volumetric {
    pub cfg: VolumetricConfig,
    pub scene_scale: f64,
    pub slot_dim: usize,
    pub bg: VolumeNet,
    pub fg: VolumeNet,
}

fn dense_linear(x: &Tensor, l: &Linear, act: Activation) -> candle_core::Result<Tensor> {
    let b = l
        .bias()
        .ok_or_else(|| candle_core::Error::Msg("volumetric: layer without bias".into()))?;
    dense(x, &l.weight().t()?, b, act)
}

impl VolumeNet {
    fn new(cfg: &VolumetricConfig, slot_dim: usize, vb: VarBuilder) -> candle_core::Result<Self> {
        let (w, e) = (cfg.hidden, cfg.pos_dim());
        let n = cfg.layers_before_skip + cfg.layers_after_skip;
        let layers = (0..n)
            .map(|i| {
                let input = if i == 0 {
                    e + slot_dim
                } else if i == cfg.layers_before_skip {
                    w + e + slot_dim
                } else {
                    w
                };
                linear(input, w, vb.pp(format!("layers.{i}")))
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(VolumeNet {
            layers,
            density: linear(w, 1, vb.pp("density"))?,
            color_hidden: linear(w, cfg.color_hidden, vb.pp("color.layers.0"))?,
            color_out: linear(cfg.color_hidden, 3, vb.pp("color.layers.1"))?,
        })
    }

    /// enc [P, E] points of one slot, z [D] → (σ [P], colour [P, 3]); plain concatenation.
    fn forward(
        &self,
        enc: &Tensor,
        z: &Tensor,
        before: usize,
    ) -> candle_core::Result<(Tensor, Tensor)> {
        let p = enc.dim(0)?;
        let zs = z.unsqueeze(0)?.broadcast_as((p, z.dim(0)?))?;
        let input = Tensor::cat(&[enc, &zs], 1)?;
        let mut h = input.clone();
        for (i, layer) in self.layers.iter().enumerate() {
            let x = if i == 0 {
                input.clone()
            } else if i == before {
                Tensor::cat(&[&h, &input], 1)?
            } else {
                h
            };
            h = dense_linear(&x, layer, Activation::Relu)?;
        }
        let sigma = dense_linear(&h, &self.density, Activation::Relu)?.squeeze(1)?;
        let c = dense_linear(&h, &self.color_hidden, Activation::Relu)?;
        let color =
            candle_nn::ops::sigmoid(&dense_linear(&c, &self.color_out, Activation::Identity)?)?;
        Ok((sigma, color))
    }
}

/// What [`Volumetric::composite`] returns for R rays and S slots.
#[derive(Clone, Debug)]
pub struct VolumeRender {
    /// [R, 3].
    pub rgb: Tensor,
    /// [R, S], each row sums to 1 (background first).
    pub weights: Tensor,
    /// Expected depth of each slot along the ray [R, S], world units.
    pub depth: Tensor,
}

impl Volumetric {
    pub fn new(cfg: &Config, vb: VarBuilder) -> candle_core::Result<Volumetric> {
        let vcfg = cfg
            .volumetric
            .clone()
            .ok_or_else(|| candle_core::Error::Msg("not a volumetric config".into()))?;
        Ok(Volumetric {
            bg: VolumeNet::new(&vcfg, cfg.slot_dim, vb.pp("bg"))?,
            fg: VolumeNet::new(&vcfg, cfg.slot_dim, vb.pp("fg"))?,
            scene_scale: cfg.scene_scale,
            slot_dim: cfg.slot_dim,
            cfg: vcfg,
        })
    }

    /// Distances of the N sample midpoints from the ray origin (world units) and their spacing.
    pub fn sample_depths(&self, n: usize) -> (Vec<f64>, f64) {
        let delta = (self.cfg.far - self.cfg.near) / n as f64;
        (
            (0..n)
                .map(|i| self.cfg.near + (i as f64 + 0.5) * delta)
                .collect(),
            delta,
        )
    }

    /// Positional encoding of sample points: for every slot frame (background = world first,
    /// then `slot_to_world[k]`) and ray, the N samples → [S, R·N, E] values, ray-major.
    pub fn encode_points(
        &self,
        slot_to_world: &[DMat4],
        origins: &[DVec3],
        dirs: &[DVec3],
        n: usize,
    ) -> Vec<f32> {
        let e = self.cfg.pos_dim();
        let (depths, _) = self.sample_depths(n);
        let mut frames = vec![DMat4::IDENTITY];
        frames.extend(slot_to_world.iter().map(|m| m.inverse()));
        let mut out = vec![0f32; frames.len() * origins.len() * n * e];
        let mut row = 0;
        for inv in &frames {
            for (o, d) in origins.iter().zip(dirs) {
                let d = d.normalize();
                for t in &depths {
                    let p = inv.transform_point3(*o + *t * d) / self.scene_scale;
                    encode_point(
                        [p.x, p.y, p.z],
                        self.cfg.pos_freqs,
                        &mut out[row * e..(row + 1) * e],
                    );
                    row += 1;
                }
            }
        }
        out
    }

    /// The networks on encoded points: enc [S, P, E] (slot 0 the background), latents
    /// [S, D] → (σ [S, P], colour [S, P, 3]).
    pub fn forward(&self, enc: &Tensor, latents: &Tensor) -> candle_core::Result<(Tensor, Tensor)> {
        let s = enc.dim(0)?;
        let (mut sigmas, mut colors) = (Vec::with_capacity(s), Vec::with_capacity(s));
        for i in 0..s {
            let net = if i == 0 { &self.bg } else { &self.fg };
            let (sg, c) =
                net.forward(&enc.get(i)?, &latents.get(i)?, self.cfg.layers_before_skip)?;
            sigmas.push(sg);
            colors.push(c);
        }
        Ok((Tensor::stack(&sigmas, 0)?, Tensor::stack(&colors, 0)?))
    }

    /// Density-weighted slot composition and alpha compositing: σ [S, R, N], colour
    /// [S, R, N, 3] → colour, weights and depths per ray (see the module documentation).
    pub fn composite(&self, sigma: &Tensor, color: &Tensor) -> candle_core::Result<VolumeRender> {
        let (s, r, n) = sigma.dims3()?;
        let dev = sigma.device();
        let (depths, delta) = self.sample_depths(n);
        let t = Tensor::from_vec(
            depths.iter().map(|v| *v as f32).collect::<Vec<_>>(),
            (1, n),
            dev,
        )?;
        let total = sigma.sum(0)?; // [R, N]
        let share = sigma.broadcast_div(&(&total + 1e-10)?)?; // [S, R, N]
        let c = (color.broadcast_mul(&share.unsqueeze(3)?)?).sum(0)?; // [R, N, 3]
        let alpha = (1.0 - (&total * (-delta))?.exp()?)?; // [R, N]
                                                          // T_i = exp(−Σ_{j<i} σ_j·δ): exclusive cumulative sum.
        let optical = (&total * delta)?.cumsum(1)?;
        let exclusive = (optical.clone() - (&total * delta)?)?;
        let trans = exclusive.neg()?.exp()?;
        let w = (trans * &alpha)?; // [R, N]
        let rgb = c.broadcast_mul(&w.unsqueeze(2)?)?.sum(1)?; // [R, 3]
        let slot_w = share.broadcast_mul(&w.unsqueeze(0)?)?; // [S, R, N]
        let per_slot = slot_w.sum(D::Minus1)?.t()?; // [R, S]
        let depth_num = slot_w
            .broadcast_mul(&t.unsqueeze(0)?)?
            .sum(D::Minus1)?
            .t()?;
        let left = (1.0 - w.sum_keepdim(1)?)?; // [R, 1]
        let bg_extra = Tensor::cat(&[&left, &Tensor::zeros((r, s - 1), left.dtype(), dev)?], 1)?;
        let weights = (per_slot.clone() + bg_extra)?;
        // A slot with no weight along the ray: its depth is the far bound.
        let far = Tensor::full(self.cfg.far as f32, (r, s), dev)?;
        let depth = per_slot
            .gt(0.0)?
            .where_cond(&(depth_num / per_slot.maximum(1e-30)?)?, &far)?;
        Ok(VolumeRender {
            rgb,
            weights,
            depth,
        })
    }

    /// The reference render of R rays with N samples (candle ops, plain concatenation):
    /// colour [R, 3], weights [R, S], depths [R, S]. Memory grows with R·N·S: for tests and
    /// small batches; `crate::render::fast` renders frames.
    pub fn render_reference(
        &self,
        latents: &Tensor,
        slot_to_world: &[DMat4],
        origins: &[DVec3],
        dirs: &[DVec3],
        n: usize,
    ) -> Result<VolumeRender> {
        let s = 1 + slot_to_world.len();
        if latents.dims() != [s, self.slot_dim] {
            bail!("volumetric: latents {:?} for {s} slots", latents.dims());
        }
        let r = origins.len();
        let e = self.cfg.pos_dim();
        let enc = Tensor::from_vec(
            self.encode_points(slot_to_world, origins, dirs, n),
            (s, r * n, e),
            latents.device(),
        )?;
        let (sigma, color) = self.forward(&enc, latents)?;
        Ok(self.composite(&sigma.reshape((s, r, n))?, &color.reshape((s, r, n, 3))?)?)
    }
}

/// γ(p) of one point into `out` (E values): p, then sin and cos of 2^k·π·p for k < L, as
/// [p_x, p_y, p_z, sin_0(x, y, z), cos_0(x, y, z), sin_1(…), …], by the double-angle recurrence
/// in f64.
pub fn encode_point(p: [f64; 3], freqs: usize, out: &mut [f32]) {
    for c in 0..3 {
        out[c] = p[c] as f32;
        let (mut sin, mut cos) = (std::f64::consts::PI * p[c]).sin_cos();
        for f in 0..freqs {
            out[3 + 6 * f + c] = sin as f32;
            out[6 + 6 * f + c] = cos as f32;
            (sin, cos) = (2.0 * sin * cos, 1.0 - 2.0 * sin * sin);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Colf;
    use candle_core::Device;

    #[test]
    fn positional_encoding_matches_direct_sin_cos() {
        let mut out = vec![0f32; 33];
        let p = [0.3, -0.71, 0.05];
        encode_point(p, 5, &mut out);
        for c in 0..3 {
            assert_eq!(out[c], p[c] as f32);
            for f in 0..5 {
                let arg = (1u64 << f) as f64 * std::f64::consts::PI * p[c];
                assert!((out[3 + 6 * f + c] as f64 - arg.sin()).abs() < 1e-6);
                assert!((out[6 + 6 * f + c] as f64 - arg.cos()).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn composite_weights_sum_to_one_and_an_opaque_front_slot_wins() {
        let model = Colf::init(&Config::volumetric(), 0).unwrap();
        let vol = model.model().volumetric().unwrap();
        let dev = Device::Cpu;
        // 2 slots, 1 ray, 4 samples: the foreground slot is dense at sample 1, the background
        // only at sample 3.
        let sigma = Tensor::from_vec(
            vec![0f32, 0.0, 0.0, 50.0, 0.0, 50.0, 0.0, 0.0],
            (2, 1, 4),
            &dev,
        )
        .unwrap();
        let mut col = vec![0f32; 24];
        for i in 0..4 {
            col[i * 3] = 1.0; // background red
            col[12 + i * 3 + 2] = 1.0; // slot blue
        }
        let color = Tensor::from_vec(col, (2, 1, 4, 3), &dev).unwrap();
        let out = vol.composite(&sigma, &color).unwrap();
        let w = out.weights.to_vec2::<f32>().unwrap();
        assert!((w[0][0] + w[0][1] - 1.0).abs() < 1e-5);
        assert!(w[0][1] > 0.99, "{w:?}");
        let rgb = out.rgb.to_vec2::<f32>().unwrap();
        assert!(rgb[0][2] > 0.99 && rgb[0][0] < 0.01, "{rgb:?}");
        let depth = out.depth.to_vec2::<f32>().unwrap();
        let (t, _) = vol.sample_depths(4);
        assert!((depth[0][1] as f64 - t[1]).abs() < 1e-3, "{depth:?}");
    }
}
