//! The image encoder of uORF / COLF (supplement §1.1): image + 4 coordinate channels → a 3×3
//! conv U-Net → a feature grid, flattened to tokens [B, N, C].
//!
//! Layers (ReLU after each), as in uORF's `Encoder`:
//! `down1` (stride `encoder_first_stride`), `down2` and `down3` (stride 2), `up3` then ×2
//! bilinear upsampling, `up2` on [up3, down2] then ×2 upsampling, `up1` on [up2, down1]. The
//! supplement's "bilinear upsampling on the last three" is this decoder half: the last three
//! convs bring the grid back up to `down1`'s resolution.
//!
//! Upsampling is a fixed interpolation matrix applied as matmuls (out = A_h · X · A_wᵀ) because
//! candle's `upsample_bilinear2d` has no backward. Tensor names: `encoder.{down1,down2,down3,
//! up3,up2,up1}.{weight,bias}` (weight [out, in, 3, 3]).

use super::config::Config;
use super::conv::{conv3x3, upsample2x};
use super::fused::Activation;
use candle_core::{Device, Result, Tensor};
use candle_nn::{conv2d, Conv2d, Conv2dConfig, VarBuilder};

/// The 1-D bilinear ×2 upsampling matrix [2n, n] (PyTorch `align_corners=False` semantics).
pub fn upsample_matrix(n: usize) -> Vec<f32> {
    let mut a = vec![0f32; 2 * n * n];
    for i in 0..2 * n {
        let src = ((i as f64 + 0.5) / 2.0 - 0.5).max(0.0);
        let i0 = (src.floor() as usize).min(n - 1);
        let i1 = (i0 + 1).min(n - 1);
        let lambda = (src - i0 as f64) as f32;
        a[i * n + i0] += 1.0 - lambda;
        a[i * n + i1] += lambda;
    }
    a
}

/// Resizes an RGB image (h×w×3, row-major) to out_h×out_w with a separable triangle
/// ("bilinear") filter whose support widens when shrinking, so large photos are averaged rather
/// than aliased; identical to bilinear (half-pixel centres) when enlarging. Deterministic.
pub fn resize_bilinear(rgb: &[f32], h: usize, w: usize, out_h: usize, out_w: usize) -> Vec<f32> {
    assert_eq!(rgb.len(), h * w * 3, "image buffer size");
    if h == out_h && w == out_w {
        return rgb.to_vec();
    }
    // Weights of each output sample over the input samples along one axis.
    fn weights(n_in: usize, n_out: usize) -> Vec<Vec<(usize, f32)>> {
        let scale = n_in as f64 / n_out as f64;
        let support = scale.max(1.0);
        (0..n_out)
            .map(|o| {
                let centre = (o as f64 + 0.5) * scale - 0.5;
                let lo = (centre - support).floor().max(0.0) as usize;
                let hi = ((centre + support).ceil() as usize).min(n_in - 1);
                let mut taps: Vec<(usize, f32)> = (lo..=hi)
                    .filter_map(|i| {
                        let t = 1.0 - ((i as f64 - centre) / support).abs();
                        (t > 0.0).then_some((i, t as f32))
                    })
                    .collect();
                if taps.is_empty() {
                    taps.push(((centre.round().max(0.0) as usize).min(n_in - 1), 1.0));
                }
                let total: f32 = taps.iter().map(|t| t.1).sum();
                taps.iter_mut().for_each(|t| t.1 /= total);
                taps
            })
            .collect()
    }
    let wx = weights(w, out_w);
    let wy = weights(h, out_h);
    // Horizontal pass: h × out_w × 3.
    let mut tmp = vec![0f32; h * out_w * 3];
    for y in 0..h {
        for (x, taps) in wx.iter().enumerate() {
            for c in 0..3 {
                tmp[(y * out_w + x) * 3 + c] = taps
                    .iter()
                    .map(|&(i, t)| t * rgb[(y * w + i) * 3 + c])
                    .sum();
            }
        }
    }
    let mut out = vec![0f32; out_h * out_w * 3];
    for (y, taps) in wy.iter().enumerate() {
        for x in 0..out_w {
            for c in 0..3 {
                out[(y * out_w + x) * 3 + c] = taps
                    .iter()
                    .map(|&(i, t)| t * tmp[(i * out_w + x) * 3 + c])
                    .sum();
            }
        }
    }
    out
}

/// The encoder's input tensor [1, 3, S, S] (S = `encoder_size`) from an RGB image h×w×3 in
/// [0, 1]; values are clamped to [0, 1] (non-finite values become 0).
pub fn image_tensor(cfg: &Config, rgb: &[f32], h: usize, w: usize, dev: &Device) -> Result<Tensor> {
    let s = cfg.encoder_size;
    let resized = resize_bilinear(rgb, h, w, s, s);
    let mut chw = vec![0f32; 3 * s * s];
    for (p, px) in resized.chunks_exact(3).enumerate() {
        for c in 0..3 {
            let v = px[c];
            chw[c * s * s + p] = if v.is_finite() {
                v.clamp(0.0, 1.0)
            } else {
                0.0
            };
        }
    }
    Tensor::from_vec(chw, (1, 3, s, s), dev)
}

/// The conv U-Net.
#[derive(Clone, Debug)]
pub struct Encoder {
    down1: Conv2d,
    down2: Conv2d,
    down3: Conv2d,
    up3: Conv2d,
    up2: Conv2d,
    up1: Conv2d,
    /// Stride of `down1` (1 or 2).
    first_stride: usize,
    /// Coordinate channels x, 2−x, y, 2−y [1, 4, S, S].
    coords: Tensor,
    /// Bilinear ×2 upsampling matrices A [2n, n] from the ¼ grid, then from the ½ grid.
    upsample_quarter: Tensor,
    upsample_half: Tensor,
    size: usize,
}

fn conv(cin: usize, cout: usize, stride: usize, vb: VarBuilder) -> Result<Conv2d> {
    let cfg = Conv2dConfig {
        padding: 1,
        stride,
        ..Default::default()
    };
    conv2d(cin, cout, 3, cfg, vb)
}

fn upsampler(n: usize, dev: &Device) -> Result<Tensor> {
    Tensor::from_vec(upsample_matrix(n), (2 * n, n), dev)
}

/// One 3×3 conv layer (candle's parameter layout) with a ReLU, on channels-last maps.
fn conv_relu(layer: &Conv2d, x: &Tensor, stride: usize) -> Result<Tensor> {
    let bias = layer
        .bias()
        .ok_or_else(|| candle_core::Error::Msg("encoder convs have biases".into()))?;
    conv3x3(x, layer.weight(), bias, stride, Activation::Relu)
}

impl Encoder {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Encoder> {
        let (c1, c2, f) = (
            cfg.encoder_channels,
            cfg.encoder_channels_low,
            cfg.feature_dim,
        );
        let s = cfg.encoder_size;
        let dev = vb.device().clone();
        let mut coords = vec![0f32; 4 * s * s];
        let lin = |i: usize| -1.0 + 2.0 * i as f32 / (s - 1) as f32;
        for y in 0..s {
            for x in 0..s {
                let p = y * s + x;
                coords[p] = lin(x);
                coords[s * s + p] = 2.0 - lin(x);
                coords[2 * s * s + p] = lin(y);
                coords[3 * s * s + p] = 2.0 - lin(y);
            }
        }
        let grid = cfg.token_grid();
        Ok(Encoder {
            down1: conv(7, c1, cfg.encoder_first_stride, vb.pp("down1"))?,
            down2: conv(c1, c2, 2, vb.pp("down2"))?,
            down3: conv(c2, c2, 2, vb.pp("down3"))?,
            up3: conv(c2, c2, 1, vb.pp("up3"))?,
            up2: conv(2 * c2, c2, 1, vb.pp("up2"))?,
            up1: conv(c2 + c1, f, 1, vb.pp("up1"))?,
            first_stride: cfg.encoder_first_stride,
            coords: Tensor::from_vec(coords, (1, 4, s, s), &dev)?,
            upsample_quarter: upsampler(grid / 4, &dev)?,
            upsample_half: upsampler(grid / 2, &dev)?,
            size: s,
        })
    }

    /// images [B, 3, S, S] in [0, 1] → tokens [B, grid², feature_dim]. Inside, maps are
    /// channels-last [B, H, W, C] (see `conv.rs`).
    pub fn forward(&self, images: &Tensor) -> Result<Tensor> {
        let (b, _, h, w) = images.dims4()?;
        if h != self.size || w != self.size {
            candle_core::bail!("encoder expects {0}×{0} images, got {h}×{w}", self.size);
        }
        let coords = self.coords.broadcast_as((b, 4, h, w))?;
        let x = Tensor::cat(&[images, &coords], 1)?
            .permute((0, 2, 3, 1))?
            .contiguous()?;
        let down1 = conv_relu(&self.down1, &x, self.first_stride)?;
        let down2 = conv_relu(&self.down2, &down1, 2)?;
        let down3 = conv_relu(&self.down3, &down2, 2)?;
        let up3 = upsample2x(&conv_relu(&self.up3, &down3, 1)?, &self.upsample_quarter)?;
        let up2 = conv_relu(&self.up2, &Tensor::cat(&[&up3, &down2], 3)?, 1)?;
        let up2 = upsample2x(&up2, &self.upsample_half)?;
        let features = conv_relu(&self.up1, &Tensor::cat(&[&up2, &down1], 3)?, 1)?;
        // [B, g, g, C] → [B, g², C]
        let (_, g, _, c) = features.dims4()?;
        features.reshape((b, g * g, c))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn upsample_matrix_matches_pytorch_align_corners_false() {
        // torch.nn.functional.interpolate([0, 1, 2], scale_factor=2, mode="linear")
        // = [0, 0.25, 0.75, 1.25, 1.75, 2].
        let a = upsample_matrix(3);
        let x = [0f32, 1.0, 2.0];
        let out: Vec<f32> = (0..6)
            .map(|i| (0..3).map(|j| a[i * 3 + j] * x[j]).sum())
            .collect();
        let want = [0.0, 0.25, 0.75, 1.25, 1.75, 2.0];
        for (o, w) in out.iter().zip(want) {
            assert!((o - w).abs() < 1e-6, "{out:?}");
        }
    }

    #[test]
    fn resize_is_identity_at_same_size_and_averages_when_halving() {
        let img: Vec<f32> = (0..4 * 4 * 3).map(|i| (i % 7) as f32 / 7.0).collect();
        assert_eq!(resize_bilinear(&img, 4, 4, 4, 4), img);
        let half = resize_bilinear(&img, 4, 4, 2, 2);
        assert_eq!(half.len(), 12);
        assert!(half.iter().all(|v| (0.0..=1.0).contains(v)));
        // A constant image stays constant at any size.
        let flat = vec![0.3f32; 5 * 7 * 3];
        for (oh, ow) in [(64, 64), (2, 3), (1, 1)] {
            let r = resize_bilinear(&flat, 5, 7, oh, ow);
            assert!(r.iter().all(|v| (v - 0.3).abs() < 1e-6));
        }
    }
}
