//! Background-aware slot attention (uORF; COLF supplement Algorithm 1): one background slot and
//! K foreground slots compete for the encoder's tokens over `slot_iters` rounds.
//!
//! Background and foreground have their own learned Gaussian (μ, log σ), slot layer norm, query
//! projection, GRU and residual MLP; the input layer norm and the key/value projections are
//! shared. The softmax runs over the slots (bg + fg), so slots compete for each token.
//! K is a runtime argument (any K ≥ 0). The initial slot noise is drawn from the caller's seeded
//! `StdRng` — never candle's RNG, never re-seeded to a constant here (a trap of the authors'
//! code, where every call drew the same noise).
//!
//! Tensor names (prefix `slot_attention.`): `norm_input.{weight,bias}`, `to_k.weight`,
//! `to_v.weight`, and for each branch `bg.` / `fg.`: `mu`, `log_sigma` [D],
//! `norm_slot.{weight,bias}`, `to_q.weight` [D, D], `gru.{weight_ih_l0,weight_hh_l0,bias_ih_l0,
//! bias_hh_l0}`, `norm_mlp.{weight,bias}`, `mlp.layers.{0,1}.{weight,bias}`.

use super::config::Config;
use super::layers::{LayerNormSlow, Mlp, OutputLayer};
use candle_core::{Module, Result, Tensor, D};
use candle_nn::rnn::{gru, GRUConfig, GRUState, GRU, RNN};
use candle_nn::{linear_no_bias, Init, Linear, VarBuilder};
use rand::rngs::StdRng;
use rand::Rng;
use rand_distr::StandardNormal;

/// Per-branch (background or foreground) parameters.
#[derive(Clone, Debug)]
struct SlotBranch {
    mu: Tensor,
    log_sigma: Tensor,
    norm_slot: LayerNormSlow,
    to_q: Linear,
    gru: GRU,
    norm_mlp: LayerNormSlow,
    mlp: Mlp,
}

impl SlotBranch {
    fn new(cfg: &Config, vb: VarBuilder) -> Result<SlotBranch> {
        let d = cfg.slot_dim;
        // uORF: μ ~ N(0, 1); log σ Xavier-uniform on a [1, 1, D] tensor.
        let bound = (3.0 / d as f64).sqrt();
        Ok(SlotBranch {
            mu: vb.get_with_hints(
                d,
                "mu",
                Init::Randn {
                    mean: 0.0,
                    stdev: 1.0,
                },
            )?,
            log_sigma: vb.get_with_hints(
                d,
                "log_sigma",
                Init::Uniform {
                    lo: -bound,
                    up: bound,
                },
            )?,
            norm_slot: LayerNormSlow::new(d, vb.pp("norm_slot"))?,
            to_q: linear_no_bias(d, d, vb.pp("to_q"))?,
            gru: gru(d, d, GRUConfig::default(), vb.pp("gru"))?,
            norm_mlp: LayerNormSlow::new(d, vb.pp("norm_mlp"))?,
            mlp: Mlp::new(
                d,
                cfg.slot_mlp_hidden,
                1,
                d,
                OutputLayer::Plain,
                vb.pp("mlp"),
            )?,
        })
    }

    /// Initial slots μ + σ·ε for noise ε [B, n, D].
    fn initial(&self, noise: &Tensor) -> Result<Tensor> {
        noise
            .broadcast_mul(&self.log_sigma.exp()?)?
            .broadcast_add(&self.mu)
    }

    /// GRU update with `updates` as input and the previous slots as state, then the residual
    /// MLP. slots, updates: [B, n, D].
    fn update(&self, slots: &Tensor, updates: &Tensor) -> Result<Tensor> {
        let (b, n, d) = slots.dims3()?;
        let state = GRUState {
            h: slots.reshape((b * n, d))?,
        };
        let slots = self
            .gru
            .step(&updates.reshape((b * n, d))?, &state)?
            .h
            .reshape((b, n, d))?;
        slots.add(&self.mlp.forward(&self.norm_mlp.forward(&slots)?)?)
    }
}

/// What slot attention returns.
#[derive(Clone, Debug)]
pub struct SlotOutput {
    /// Foreground slots [B, K, D].
    pub fg: Tensor,
    /// Background slot [B, D].
    pub bg: Tensor,
    /// Share of the image's attention each foreground slot took in the last round [B, K]
    /// (with the background's share, the K + 1 values sum to 1).
    pub fg_mass: Tensor,
    /// The background's share [B].
    pub bg_mass: Tensor,
    /// Where each foreground slot attends in the image: the attention-weighted mean token
    /// position (x right, y down, in [0, 1] of the image's width and height) in the last round
    /// [B, K, 2]; no gradient flows through it (it only places slot frames, see `frames.rs`).
    pub fg_centroid: Tensor,
    /// How far down the image each foreground slot's attention reaches [B, K]: the mean
    /// token row plus √3 standard deviations (the lower edge of a uniform spread), in [0, 1]
    /// of the image's height; like `fg_centroid`, only for placing frames (`frames.rs`).
    pub fg_bottom: Tensor,
    /// log of the last round's attention over the slots per token [B, N, 1 + K] (background
    /// first), by log-softmax (for losses on the attention).
    pub log_attention: Tensor,
}

/// The side g of a square grid of `n_tokens` tokens.
fn grid_side(n_tokens: usize) -> Result<usize> {
    let g = (n_tokens as f64).sqrt().round() as usize;
    if g * g != n_tokens {
        candle_core::bail!("{n_tokens} tokens do not form a square grid");
    }
    Ok(g)
}

/// Centres of the tokens of a square g×g grid (row-major), as (x, y) in [0, 1] [N, 2].
fn token_positions(n_tokens: usize, device: &candle_core::Device) -> Result<Tensor> {
    let g = grid_side(n_tokens)?;
    let xy: Vec<f32> = (0..n_tokens)
        .flat_map(|t| {
            let (x, y) = (t % g, t / g);
            [(x as f32 + 0.5) / g as f32, (y as f32 + 0.5) / g as f32]
        })
        .collect();
    Tensor::from_vec(xy, (n_tokens, 2), device)
}

/// Where slots attend, from their weights over a square grid of tokens [B, N, K] (summing to
/// 1 over the tokens): the weighted mean token position (x, y) [B, K, 2], and how far down the
/// attention reaches [B, K], the mean row plus √3 standard deviations (the lower edge of a
/// uniform spread), in [0, 1].
fn where_slots_attend(weights: &Tensor) -> Result<(Tensor, Tensor)> {
    let grid = token_positions(weights.dim(1)?, weights.device())?; // [N, 2]
    let per_slot = weights.t()?; // [B, K, N]
    let centroid = per_slot.broadcast_matmul(&grid)?.contiguous()?;
    // The rows' second moment from (y, y²) per token.
    let y = grid.narrow(1, 1, 1)?;
    let rows = Tensor::cat(&[&y, &y.sqr()?], 1)?;
    let moments = per_slot.broadcast_matmul(&rows)?; // [B, K, 2]
    let mean_y = moments.narrow(2, 0, 1)?;
    let variance = (moments.narrow(2, 1, 1)? - mean_y.sqr()?)?.relu()?;
    let bottom = (mean_y + (variance * 3.0)?.sqrt()?)?.clamp(0.0, 1.0)?;
    Ok((centroid, bottom.squeeze(2)?.contiguous()?))
}

impl SlotOutput {
    /// Places the foreground slots (`fg_centroid`, `fg_bottom`) from the part of their last
    /// round's attention on the tokens `within` [B, N] weighs (≥ 0: e.g. the share of each
    /// token's pixels that are object candidates), each slot's attention times `within`
    /// normalised over the tokens; a slot with less than `min_share` of its attention there
    /// keeps its placement.
    pub fn attend_within(&mut self, within: &Tensor, min_share: f64) -> Result<()> {
        let k = self.fg_centroid.dim(1)?;
        if k == 0 {
            return Ok(());
        }
        let attention = self.log_attention.detach().exp()?.narrow(2, 1, k)?; // [B, N, K]
        let inside = attention.broadcast_mul(&within.unsqueeze(2)?)?;
        let mass = inside.sum_keepdim(1)?; // [B, 1, K]
        let weights = inside.broadcast_div(&(&mass + 1e-20)?)?;
        let (centroid, bottom) = where_slots_attend(&weights)?;
        let keep = mass
            .lt(&(attention.sum_keepdim(1)? * min_share)?)?
            .squeeze(1)?; // [B, K]
        let keep_xy = keep.unsqueeze(2)?.broadcast_as(centroid.shape())?;
        self.fg_centroid = keep_xy.where_cond(&self.fg_centroid, &centroid)?;
        self.fg_bottom = keep.where_cond(&self.fg_bottom, &bottom)?;
        Ok(())
    }

    /// [`SlotOutput::attend_within`] the object pixels of each image: (pixels, h, w), row-major,
    /// 1 on object pixels and 0 elsewhere, one per image of the batch; the share of each
    /// token's pixels that are objects weighs it.
    pub fn attend_within_pixels(
        &mut self,
        objects: &[(&[f32], usize, usize)],
        min_share: f64,
    ) -> Result<()> {
        let tokens = self.log_attention.dim(1)?;
        let grid = grid_side(tokens)?;
        let mut shares = Vec::with_capacity(objects.len() * tokens);
        for &(pixels, h, w) in objects {
            if pixels.len() != h * w {
                candle_core::bail!("{} object pixels for a {w}×{h} image", pixels.len());
            }
            shares.extend(token_shares(pixels, h, w, grid));
        }
        let within =
            Tensor::from_vec(shares, (objects.len(), tokens), self.log_attention.device())?;
        self.attend_within(&within, min_share)
    }
}

/// The share of each cell of a g×g grid (row-major) covered by `pixels` (h×w, row-major, 1 on
/// the pixels to keep and 0 elsewhere): a box filter from the image to the token grid.
pub fn token_shares(pixels: &[f32], h: usize, w: usize, g: usize) -> Vec<f32> {
    let mut sum = vec![0f32; g * g];
    let mut count = vec![0f32; g * g];
    for j in 0..h {
        let row = (j * g / h.max(1)).min(g - 1);
        for i in 0..w {
            let col = (i * g / w.max(1)).min(g - 1);
            sum[row * g + col] += pixels[j * w + i];
            count[row * g + col] += 1.0;
        }
    }
    sum.iter()
        .zip(&count)
        .map(|(s, c)| if *c > 0.0 { s / c } else { 0.0 })
        .collect()
}

/// The slot encoder.
#[derive(Clone, Debug)]
pub struct SlotAttention {
    norm_input: LayerNormSlow,
    to_k: Linear,
    to_v: Linear,
    bg: SlotBranch,
    fg: SlotBranch,
    dim: usize,
    iters: usize,
}

impl SlotAttention {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<SlotAttention> {
        Ok(SlotAttention {
            norm_input: LayerNormSlow::new(cfg.feature_dim, vb.pp("norm_input"))?,
            to_k: linear_no_bias(cfg.feature_dim, cfg.slot_dim, vb.pp("to_k"))?,
            to_v: linear_no_bias(cfg.feature_dim, cfg.slot_dim, vb.pp("to_v"))?,
            bg: SlotBranch::new(cfg, vb.pp("bg"))?,
            fg: SlotBranch::new(cfg, vb.pp("fg"))?,
            dim: cfg.slot_dim,
            iters: cfg.slot_iters,
        })
    }

    /// Draws the initial-slot noise [B, 1 + K, D] from `rng` (per image: background first,
    /// then the K foreground slots, row-major).
    pub fn draw_noise(&self, b: usize, k: usize, rng: &mut StdRng) -> Result<Tensor> {
        let n = b * (1 + k) * self.dim;
        let noise: Vec<f32> = (0..n)
            .map(|_| rng.sample::<f32, _>(StandardNormal))
            .collect();
        Tensor::from_vec(noise, (b, 1 + k, self.dim), self.mu_device())
    }

    fn mu_device(&self) -> &candle_core::Device {
        self.bg.mu.device()
    }

    /// tokens [B, N, C] → slots, with K foreground slots and noise drawn from `rng`.
    pub fn forward(&self, tokens: &Tensor, k: usize, rng: &mut StdRng) -> Result<SlotOutput> {
        let b = tokens.dim(0)?;
        let noise = self.draw_noise(b, k, rng)?;
        self.forward_with_noise(tokens, &noise)
    }

    /// As `forward`, with the initial noise [B, 1 + K, D] given.
    pub fn forward_with_noise(&self, tokens: &Tensor, noise: &Tensor) -> Result<SlotOutput> {
        let (b, n_tokens, _) = tokens.dims3()?;
        let (_, s, d) = noise.dims3()?;
        let k = s - 1;
        let x = self.norm_input.forward(tokens)?;
        let keys = self.to_k.forward(&x)?; // [B, N, D]
        let values = self.to_v.forward(&x)?; // [B, N, D]
        let scale = 1.0 / (d as f64).sqrt();

        let mut bg = self.bg.initial(&noise.narrow(1, 0, 1)?)?; // [B, 1, D]
        let mut fg = if k > 0 {
            Some(self.fg.initial(&noise.narrow(1, 1, k)?)?) // [B, K, D]
        } else {
            None
        };
        let mut attn = None;
        let mut token_weights = None;
        let mut last_logits = None;
        for _ in 0..self.iters {
            let q_bg = self.bg.to_q.forward(&self.bg.norm_slot.forward(&bg)?)?;
            let q = match &fg {
                Some(fg) => {
                    let q_fg = self.fg.to_q.forward(&self.fg.norm_slot.forward(fg)?)?;
                    Tensor::cat(&[&q_bg, &q_fg], 1)?
                }
                None => q_bg,
            }; // [B, S, D]
            let logits = (keys.matmul(&q.t()?)? * scale)?; // [B, N, S]
                                                           // Softmax over the slots: the slots compete for every token.
            let a = (candle_nn::ops::softmax(&logits, D::Minus1)? + 1e-8)?;
            last_logits = Some(logits);
            // Weighted mean over the tokens each slot won.
            let weights = a.broadcast_div(&a.sum_keepdim(1)?)?;
            let updates = weights.t()?.matmul(&values)?; // [B, S, D]
            bg = self.bg.update(&bg, &updates.narrow(1, 0, 1)?)?;
            if let Some(f) = &fg {
                fg = Some(self.fg.update(f, &updates.narrow(1, 1, k)?)?);
            }
            attn = Some(a);
            token_weights = Some(weights);
        }
        let attn = match attn {
            Some(a) => a,
            None => candle_core::bail!("slot_iters must be positive"),
        };
        // Each slot's share of the image's attention: the mean over tokens of its softmax
        // weight (eps removed so shares sum to 1 up to rounding).
        let mass = ((attn - 1e-8)?.sum(1)? / n_tokens as f64)?.clamp(0.0, 1.0)?; // [B, S]
        let fg = match fg {
            Some(fg) => fg,
            None => Tensor::zeros((b, 0, d), tokens.dtype(), tokens.device())?,
        };
        let (fg_centroid, fg_bottom) = match token_weights {
            // The foreground's columns of the full [B, N, S] weights, as the centroids were
            // always read (the same bytes).
            Some(w) if k > 0 => {
                let (centroid, bottom) = where_slots_attend(&w.detach())?;
                (
                    centroid.narrow(1, 1, k)?.contiguous()?,
                    bottom.narrow(1, 1, k)?.contiguous()?,
                )
            }
            _ => (
                Tensor::zeros((b, k, 2), tokens.dtype(), tokens.device())?,
                Tensor::zeros((b, k), tokens.dtype(), tokens.device())?,
            ),
        };
        let log_attention = match last_logits {
            Some(l) => candle_nn::ops::log_softmax(&l, D::Minus1)?,
            None => candle_core::bail!("slot_iters must be positive"),
        };
        Ok(SlotOutput {
            fg,
            bg: bg.squeeze(1)?,
            fg_mass: mass.narrow(1, 1, k)?,
            bg_mass: mass.narrow(1, 0, 1)?.squeeze(1)?,
            fg_centroid,
            fg_bottom,
            log_attention,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A slot spread evenly over rows 2–5 and columns 1–2 of an 8×8 grid attends at their
    /// centre, and reaches down to row 5's lower edge (y = 6/8) within the √3σ estimate of a
    /// discrete spread; one on a single token reaches that token's centre.
    #[test]
    fn slots_attend_at_their_tokens_centre_and_reach_their_lower_edge() {
        let mut w = vec![0f32; 64 * 2];
        for row in 2..6 {
            for col in 1..3 {
                w[(row * 8 + col) * 2] = 1.0 / 8.0;
            }
        }
        w[(7 * 8 + 7) * 2 + 1] = 1.0;
        let weights = Tensor::from_vec(w, (1, 64, 2), &candle_core::Device::Cpu).unwrap();
        let (centroid, bottom) = where_slots_attend(&weights).unwrap();
        let centroid = centroid.to_vec3::<f32>().unwrap();
        let bottom = bottom.to_vec2::<f32>().unwrap();
        assert!((centroid[0][0][0] - 2.0 / 8.0).abs() < 1e-6);
        assert!((centroid[0][0][1] - 4.0 / 8.0).abs() < 1e-6);
        assert!((bottom[0][0] - 0.75).abs() < 0.01, "{}", bottom[0][0]);
        assert!((centroid[0][1][0] - 7.5 / 8.0).abs() < 1e-6);
        assert!((bottom[0][1] - 7.5 / 8.0).abs() < 1e-3, "{}", bottom[0][1]);
    }

    /// A 4×4 grid, background and two slots. Slot 0 spreads over the top half and a car in the
    /// lower-left quarter; placed from the object pixels, it attends at the car's centre and
    /// reaches its lower edge. Slot 1, spread evenly, has a quarter of its attention on the car:
    /// it moves there too, unless the bar is higher.
    #[test]
    fn slots_are_placed_from_their_attention_on_object_pixels() {
        use candle_core::DType;
        let dev = candle_core::Device::Cpu;
        let (g, n) = (4usize, 16usize);
        // Softmax over (background, slot 0, slot 1) per token.
        let mut attention = vec![0f32; n * 3];
        for t in 0..n {
            let (row, col) = (t / g, t % g);
            let share = if row < 2 || col < 2 {
                [0.2, 0.7, 0.1]
            } else {
                [0.9, 0.0, 0.1]
            };
            attention[t * 3..t * 3 + 3].copy_from_slice(&share);
        }
        let log_attention = Tensor::from_vec(attention.clone(), (1, n, 3), &dev)
            .unwrap()
            .clamp(1e-12, 1.0)
            .unwrap()
            .log()
            .unwrap();
        let mut out = SlotOutput {
            fg: Tensor::zeros((1, 2, 4), DType::F32, &dev).unwrap(),
            bg: Tensor::zeros((1, 4), DType::F32, &dev).unwrap(),
            fg_mass: Tensor::zeros((1, 2), DType::F32, &dev).unwrap(),
            bg_mass: Tensor::zeros(1, DType::F32, &dev).unwrap(),
            fg_centroid: Tensor::new(&[[[0.5f32, 0.4], [0.5, 0.5]]], &dev).unwrap(),
            fg_bottom: Tensor::new(&[[0.9f32, 0.9]], &dev).unwrap(),
            log_attention,
        };
        // The car: the lower-left quarter of an 8×8 image (rows 4–7, columns 0–3).
        let mut pixels = vec![0f32; 64];
        for j in 4..8 {
            for i in 0..4 {
                pixels[j * 8 + i] = 1.0;
            }
        }
        let shares = token_shares(&pixels, 8, 8, g);
        assert_eq!(shares[2 * g], 1.0);
        assert_eq!(shares[0], 0.0);
        let within = Tensor::from_vec(shares, (1, n), &dev).unwrap();
        out.attend_within(&within, 0.05).unwrap();
        let centroid = out.fg_centroid.to_vec3::<f32>().unwrap();
        let bottom = out.fg_bottom.to_vec2::<f32>().unwrap();
        // Slot 0: the car's tokens are rows 2–3, columns 0–1: centre (0.25, 0.75).
        assert!((centroid[0][0][0] - 0.25).abs() < 1e-5, "{:?}", centroid);
        assert!((centroid[0][0][1] - 0.75).abs() < 1e-5, "{:?}", centroid);
        // Its lower edge: rows at y = 0.625 and 0.875, mean 0.75 plus √3 σ (σ = 0.125).
        assert!(
            (bottom[0][0] - (0.75 + 0.125 * 3f32.sqrt())).abs() < 1e-5,
            "{:?}",
            bottom
        );
        // Slot 1 attends everywhere evenly: a quarter of its attention is on the car, so it
        // moves there too; with a higher bar it keeps its placement.
        assert!((centroid[0][1][1] - 0.75).abs() < 1e-5, "{:?}", centroid);
        let mut kept = out.clone();
        kept.fg_centroid = Tensor::new(&[[[0.5f32, 0.4], [0.5, 0.5]]], &dev).unwrap();
        kept.attend_within(&within, 0.3).unwrap();
        let centroid = kept.fg_centroid.to_vec3::<f32>().unwrap();
        assert_eq!(centroid[0][1], [0.5, 0.5]);
        assert!((centroid[0][0][1] - 0.75).abs() < 1e-5);
    }
}
