//! A trained model's weights under a config that changes its shape in ways that keep what it
//! computes, so training can continue from it (`colf-train --init M --set …`):
//! - `static_background` on a zero-background model: the background hypernetwork's output at
//!   the zero latent — the only light field it ever produced — becomes the background field's
//!   weights (`background_field.`), and `hypernet_bg.` is dropped;
//! - `static_background` (with `zero_background=true background_reader=false`) on a model whose
//!   background reads the image: as the paper does for City-Block, that background is discarded
//!   (`hypernet_bg.`, `background_reader.`) for a fresh background field, to be pretrained on the
//!   new scenes (this growth changes renders: the background starts untrained);
//! - a wider `hypernet_hidden`: each hypernetwork's new hidden units get fresh input weights and
//!   zero output weights;
//! - a wider `lfn_hidden`: every light field's new hidden units get fresh incoming weights and
//!   biases and zero outgoing weights (in a hypernetwork, the heads' rows that generate them).
//! - an image-dependent background (`zero_background` turned off): the background
//!   hypernetwork's input weights (`hypernet_bg.fc1.weight`) are zeroed. They only ever saw the
//!   zero latent, so they never received a gradient; zeroed, the slot-attention background
//!   latent changes nothing until training moves them, and it can (their gradient is the
//!   hidden layer's times the now non-zero latent).
//! - a background reader (`background_reader`, on a zero-background model whose background
//!   becomes image-dependent in the same step): fresh `background_reader.` weights, and the
//!   background hypernetwork's input weights zeroed as above, so the renders start exactly as
//!   the zero-latent model's and the gradient of those input weights is the hidden layer's times
//!   the reader's latent, which differs from image to image.
//! - `shadow_head`: a fresh shadow head, zero weights and σ = softplus(−8) ≈ 3·10⁻⁴ on every
//!   ray: each slot darkens the background by 0.03 % until training finds its shadow (the one
//!   growth that changes renders, by that much; see `heads.rs`).
//!
//! Zero outgoing weights keep every output unchanged until training moves them, and training can
//! move them: the new units are active, so those weights receive gradients. Fresh values are
//! drawn with the root-mean-square of the values they sit beside, seeded by (seed, tensor name).
//! Anything else must keep every tensor's name and shape; `Colf::reconfigured` checks that.

use super::config::Config;
use super::hypernet::BackgroundField;
use super::init::tensor_seed;
use super::ColfNet;
use anyhow::{bail, Result};
use candle_core::{DType, Device, Tensor};
use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::collections::BTreeMap;

/// `model`'s tensors (`tensors`) grown and converted for `cfg`; `name` is used in errors.
pub fn grow_tensors(
    model: &ColfNet,
    tensors: &BTreeMap<String, Tensor>,
    cfg: &Config,
    seed: u64,
    name: &str,
) -> Result<BTreeMap<String, Tensor>> {
    let old = &model.cfg;
    let mut out = tensors.clone();
    if cfg.static_background && !old.static_background {
        let Some(BackgroundField::HyperNet(hypernet_bg)) =
            model.light_field().map(|lf| &lf.background)
        else {
            bail!("{name}: `static_background` applies to light-field models only");
        };
        if !old.zero_background {
            if !cfg.zero_background || cfg.background_reader {
                bail!("{name}: this model's background depends on the image; a static background replaces it only with `zero_background=true background_reader=false` as well");
            }
            // The paper's City-Block: the image-dependent background is discarded for a
            // dedicated background field, fresh (to be pretrained on the new scenes).
            out.retain(|k, _| {
                !k.starts_with("hypernet_bg.") && !k.starts_with("background_reader.")
            });
            insert_fresh(&mut out, cfg, seed, &["background_field."])?;
            return grow_rest(out, old, cfg, seed, name);
        }
        let zero = Tensor::zeros((1, old.slot_dim), DType::F32, &Device::Cpu)?;
        for (l, layer) in hypernet_bg.forward(&zero)?.into_iter().enumerate() {
            let (_, i, o) = layer.weight.dims3()?;
            out.insert(
                format!("background_field.layers.{l}.weight"),
                layer.weight.reshape((i, o))?,
            );
            out.insert(
                format!("background_field.layers.{l}.bias"),
                layer.bias.reshape(o)?,
            );
        }
        out.retain(|k, _| !k.starts_with("hypernet_bg."));
    } else if old.static_background && !cfg.static_background {
        bail!("{name}: a static background cannot be turned back into a hypernetwork");
    }
    grow_rest(out, old, cfg, seed, name)
}

/// The growths after the background's: a zero latent made image-dependent, modules gained
/// whole, wider hypernetworks and light fields.
fn grow_rest(
    mut out: BTreeMap<String, Tensor>,
    old: &Config,
    cfg: &Config,
    seed: u64,
    name: &str,
) -> Result<BTreeMap<String, Tensor>> {
    if old.zero_background && !cfg.zero_background {
        // (A static background was refused above: it has no hypernetwork to feed.)
        if let Some(weight) = out.get_mut("hypernet_bg.fc1.weight") {
            *weight = weight.zeros_like()?;
        }
    }
    // Modules the grown model gains whole, by tensor-name prefix: taken from one fresh model.
    let mut gained = Vec::new();
    if cfg.background_reader && !old.background_reader {
        if !old.zero_background {
            bail!("{name}: a background reader grows only on a model trained with a zero background latent (its renders then start unchanged)");
        }
        gained.push("background_reader.");
    } else if old.background_reader && !cfg.background_reader && !cfg.static_background {
        bail!("{name}: a model's background reader cannot be removed (except for a static background)");
    }
    if cfg.shadow_head && !old.shadow_head {
        // A fresh shadow head: σ ≈ 3·10⁻⁴ everywhere (see `heads.rs`).
        gained.push("heads.shadow.");
    } else if old.shadow_head && !cfg.shadow_head {
        bail!("{name}: a model's shadow head cannot be removed");
    }
    insert_fresh(&mut out, cfg, seed, &gained)?;
    for (key, from, to) in [
        ("hypernet_hidden", old.hypernet_hidden, cfg.hypernet_hidden),
        ("lfn_hidden", old.lfn_hidden, cfg.lfn_hidden),
    ] {
        if to < from {
            bail!("{name}: `{key}` can grow ({from} → more), not shrink");
        }
    }
    if cfg.hypernet_hidden > old.hypernet_hidden {
        for prefix in ["hypernet_fg.", "hypernet_bg."] {
            widen_hypernet(&mut out, prefix, cfg.hypernet_hidden, seed)?;
        }
    }
    if cfg.lfn_hidden > old.lfn_hidden {
        if cfg.lfn_hidden_layers != old.lfn_hidden_layers
            || cfg.ray_fourier_freqs != old.ray_fourier_freqs
        {
            bail!("{name}: `lfn_hidden` grows only with the same `lfn_hidden_layers` and `ray_fourier_freqs`");
        }
        let grow = LayerGrowth {
            old_dims: old.lfn_dims(),
            new_dims: cfg.lfn_dims(),
            seed,
        };
        for prefix in ["hypernet_fg.", "hypernet_bg."] {
            grow.hypernet(&mut out, prefix)?;
        }
        grow.static_field(&mut out, "background_field.")?;
    }
    Ok(out)
}

/// A freshly initialised model's (`cfg`, `seed`) tensors whose names start with one of
/// `prefixes`, put into `out`: the parameters of the modules the grown model gains whole. The
/// fresh model is built once, and only when some module is gained.
fn insert_fresh(
    out: &mut BTreeMap<String, Tensor>,
    cfg: &Config,
    seed: u64,
    prefixes: &[&str],
) -> Result<()> {
    if prefixes.is_empty() {
        return Ok(());
    }
    let fresh = super::Colf::init(cfg, seed)?;
    for (key, tensor) in fresh.parameters() {
        if prefixes.iter().any(|p| key.starts_with(p)) {
            out.insert(key.clone(), tensor.clone());
        }
    }
    Ok(())
}

/// Values drawn from N(0, rms(`like`)²) in `shape`, seeded by (seed, `name`).
fn fresh_like(like: &Tensor, shape: &[usize], seed: u64, name: &str) -> Result<Tensor> {
    let values = like.flatten_all()?.to_vec1::<f32>()?;
    let rms = (values.iter().map(|v| v * v).sum::<f32>() / values.len().max(1) as f32).sqrt();
    let normal = Normal::new(0.0, rms.max(1e-6))?;
    let mut rng = StdRng::seed_from_u64(tensor_seed(seed, &format!("grow:{name}")));
    let n = shape.iter().product();
    let drawn: Vec<f32> = (0..n).map(|_| normal.sample(&mut rng)).collect();
    Ok(Tensor::from_vec(drawn, shape, &Device::Cpu)?)
}

/// Widens the hidden layer of the hypernetwork under `prefix` (if present) to `hidden` units.
fn widen_hypernet(
    tensors: &mut BTreeMap<String, Tensor>,
    prefix: &str,
    hidden: usize,
    seed: u64,
) -> Result<()> {
    let fc1_weight = format!("{prefix}fc1.weight");
    let fc1_bias = format!("{prefix}fc1.bias");
    let Some(weight) = tensors.get(&fc1_weight).cloned() else {
        return Ok(());
    };
    let (old_hidden, inputs) = weight.dims2()?;
    let extra = hidden - old_hidden;
    let new_rows = fresh_like(&weight, &[extra, inputs], seed, &fc1_weight)?;
    tensors.insert(fc1_weight, Tensor::cat(&[&weight, &new_rows], 0)?);
    let bias = tensors[&fc1_bias].clone();
    let new_bias = fresh_like(&bias, &[extra], seed, &fc1_bias)?;
    tensors.insert(fc1_bias.clone(), Tensor::cat(&[&bias, &new_bias], 0)?);
    // Every head reads the hidden layer: zero columns for the new units.
    for key in head_names(tensors, prefix) {
        if key.ends_with(".weight") {
            let head = tensors[&key].clone();
            let zeros = Tensor::zeros((head.dim(0)?, extra), DType::F32, &Device::Cpu)?;
            tensors.insert(key, Tensor::cat(&[&head, &zeros], 1)?.contiguous()?);
        }
    }
    Ok(())
}

/// The names of a hypernetwork's heads: `{prefix}layers.{l}.{weight,bias}.{weight,bias}`.
fn head_names(tensors: &BTreeMap<String, Tensor>, prefix: &str) -> Vec<String> {
    tensors
        .keys()
        .filter(|k| {
            k.strip_prefix(prefix)
                .is_some_and(|rest| rest.starts_with("layers."))
        })
        .cloned()
        .collect()
}

/// `t`'s shape with `rows` in place of its first dimension.
fn with_rows(t: &Tensor, rows: usize) -> Vec<usize> {
    let mut shape = t.dims().to_vec();
    shape[0] = rows;
    shape
}

/// Widening a light field's hidden layers from `old_dims` to `new_dims` (`Config::lfn_dims`).
struct LayerGrowth {
    old_dims: Vec<usize>,
    new_dims: Vec<usize>,
    seed: u64,
}

impl LayerGrowth {
    /// A layer-`l` weight laid out as [fan_in, fan_out, X] (X: whatever generates each entry)
    /// grown to the new fan-in (zero rows: new inputs have no effect yet) and fan-out (fresh
    /// columns: new units compute something).
    fn grow_weight(&self, t: &Tensor, l: usize, name: &str) -> Result<Tensor> {
        let (old_in, old_out) = (self.old_dims[l], self.old_dims[l + 1]);
        let (new_in, new_out) = (self.new_dims[l], self.new_dims[l + 1]);
        let x = t.elem_count() / (old_in * old_out);
        let mut t = t.reshape((old_in, old_out, x))?;
        if new_out > old_out {
            let fresh = fresh_like(&t, &[old_in, new_out - old_out, x], self.seed, name)?;
            t = Tensor::cat(&[&t, &fresh], 1)?;
        }
        if new_in > old_in {
            let zeros = Tensor::zeros((new_in - old_in, new_out, x), DType::F32, &Device::Cpu)?;
            t = Tensor::cat(&[&t, &zeros], 0)?;
        }
        Ok(t.contiguous()?)
    }

    /// A layer-`l` bias laid out as [fan_out, X], grown with fresh entries.
    fn grow_bias(&self, t: &Tensor, l: usize, name: &str) -> Result<Tensor> {
        let (old_out, new_out) = (self.old_dims[l + 1], self.new_dims[l + 1]);
        let x = t.elem_count() / old_out;
        let t = t.reshape((old_out, x))?;
        if new_out == old_out {
            return Ok(t);
        }
        let fresh = fresh_like(&t, &[new_out - old_out, x], self.seed, name)?;
        Ok(Tensor::cat(&[&t, &fresh], 0)?)
    }

    /// The heads of the hypernetwork under `prefix` (if present) generate the wider fields.
    fn hypernet(&self, tensors: &mut BTreeMap<String, Tensor>, prefix: &str) -> Result<()> {
        for l in 0..self.old_dims.len() - 1 {
            let (i, o) = (self.new_dims[l], self.new_dims[l + 1]);
            let generated_weight = format!("{prefix}layers.{l}.weight");
            let generated_bias = format!("{prefix}layers.{l}.bias");
            for part in ["weight", "bias"] {
                // Head weight [rows, H] and head bias [rows]: rows index the generated tensor.
                let key = format!("{generated_weight}.{part}");
                let Some(t) = tensors.get(&key).cloned() else {
                    return Ok(());
                };
                let grown = self.grow_weight(&t, l, &key)?;
                tensors.insert(key, grown.reshape(with_rows(&t, i * o))?);
                let key = format!("{generated_bias}.{part}");
                let t = tensors[&key].clone();
                let grown = self.grow_bias(&t, l, &key)?;
                tensors.insert(key, grown.reshape(with_rows(&t, o))?);
            }
        }
        Ok(())
    }

    /// The fixed light field under `prefix` (if present), widened.
    fn static_field(&self, tensors: &mut BTreeMap<String, Tensor>, prefix: &str) -> Result<()> {
        for l in 0..self.old_dims.len() - 1 {
            let (i, o) = (self.new_dims[l], self.new_dims[l + 1]);
            let key = format!("{prefix}layers.{l}.weight");
            let Some(t) = tensors.get(&key).cloned() else {
                return Ok(());
            };
            let grown = self.grow_weight(&t, l, &key)?.reshape((i, o))?;
            tensors.insert(key, grown);
            let key = format!("{prefix}layers.{l}.bias");
            let grown = self
                .grow_bias(&tensors[&key].clone(), l, &key)?
                .reshape(o)?;
            tensors.insert(key, grown);
        }
        Ok(())
    }
}
