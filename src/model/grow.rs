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
//! - `hypernet_per_layer`: each light-field layer's heads get their own copy of the shared
//!   hidden layer (the same light fields, each layer's hidden units then free to move);
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
//! - wider `lfn_features`: the fields' new features are fresh, and the heads read them with zero
//!   weights;
//! - more `floor_fourier_freqs`: the light fields' new input columns (the background's floor
//!   features, appended after all the old columns) are read with zero weights (the heads'
//!   rows that generate them, or the static background field's), so the renders are the same
//!   and the gradient of those weights is the floor features times the layer's;
//! - wider or deeper heads and compositor (`head_hidden`, `head_hidden_layers`,
//!   `compositor_hidden`, `compositor_hidden_layers`): new hidden units as above, new hidden
//!   layers inserted before the output layer as the identity on the old units (exact after a
//!   ReLU); see [`MlpGrowth`];
//! - a wider `slot_dim` (a whole multiple m of the old): every slot value is kept m times. What
//!   writes a slot value (the key, value and query projections' rows, μ, log σ, the layer
//!   norms, the GRU's and MLP's output rows, the background reader) is copied for each copy; what
//!   reads the slot (the GRU's and MLP's input columns, the query projection's, the
//!   hypernetworks' `fc1`) splits each old weight over the copies, so the same slots give the
//!   same keys, gates, queries and light fields; the query rows are scaled by 1/√m for the
//!   attention's 1/√D. Exact given the same initial noise in every copy (the drawn noise differs
//!   between copies: each slot starts from the mean of m draws, then the copies converge as the
//!   GRU updates them). The hypernetworks split their weights unevenly, by a seeded amount that
//!   sums to zero over the copies: copies that hold the same value give the same fields, but
//!   receive different gradients, so training and the encoding's refinement can move them apart
//!   (an even split would keep them equal forever);
//! - a wider `slot_dim` with fresh values ([`SlotValues::Fresh`], any width): the new values
//!   start at zero and the hypernetworks read them with fresh weights, so a slot's latent gains
//!   values of its own that training and the encoding's refinement can move at once (copies
//!   part slowly; issue 37 measured fresh values fitted on a frozen decoder lifting the fitted
//!   bound where copies did not). What writes a new value (the GRU's and MLP's rows, the
//!   background reader's) starts at zero, μ at zero and σ at e⁻⁶, so the new values stay near
//!   zero until training moves them; the keys and values the image's tokens give get fresh
//!   rows, the queries' zero ones. With the new values at zero, the hypernetworks' RMS norm
//!   divides by √(old/new) of the old RMS: their old columns are scaled by that, so the light
//!   fields of given latents (old values, new ones zero) are the same. Inside slot attention
//!   the layer norms see the zeros too: their gains are scaled as the RMS norm's, which is
//!   exact for slots of zero mean and close otherwise (the one growth besides the shadow head's
//!   and the static background's whose encodings move a little);
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
use anyhow::{bail, Context, Result};
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
    growth: Growth,
    name: &str,
) -> Result<BTreeMap<String, Tensor>> {
    let seed = growth.seed;
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
            return grow_rest(out, old, cfg, growth, name);
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
    grow_rest(out, old, cfg, growth, name)
}

/// How a model grows: the seed of its fresh weights, and how a wider `slot_dim` is filled.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Growth {
    pub seed: u64,
    pub slot_values: SlotValues,
}

impl Growth {
    /// Fresh weights from `seed`; a wider `slot_dim` by copies.
    pub fn seeded(seed: u64) -> Growth {
        Growth {
            seed,
            slot_values: SlotValues::Copies,
        }
    }
}

/// What a wider `slot_dim`'s new values are (see the module's notes).
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    clap::ValueEnum,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum SlotValues {
    /// Each old value kept m times (the new width a whole multiple m of the old).
    #[default]
    Copies,
    /// New values of their own, starting at zero, read with fresh weights (any wider width).
    Fresh,
}

/// The growths after the background's: a zero latent made image-dependent, modules gained
/// whole, wider hypernetworks and light fields.
fn grow_rest(
    mut out: BTreeMap<String, Tensor>,
    old: &Config,
    cfg: &Config,
    growth: Growth,
    name: &str,
) -> Result<BTreeMap<String, Tensor>> {
    let seed = growth.seed;
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
    if cfg.slot_dim != old.slot_dim {
        if cfg.slot_dim < old.slot_dim {
            bail!(
                "{name}: `slot_dim` can grow ({} → more), not shrink (asked: {})",
                old.slot_dim,
                cfg.slot_dim
            );
        }
        match growth.slot_values {
            SlotValues::Copies => {
                if !cfg.slot_dim.is_multiple_of(old.slot_dim) {
                    bail!(
                        "{name}: `slot_dim` grows by copies only to a whole multiple of {} (asked: {}; fresh values grow to any width)",
                        old.slot_dim,
                        cfg.slot_dim
                    );
                }
                SlotGrowth {
                    old: old.slot_dim,
                    new: cfg.slot_dim,
                    seed,
                }
                .apply(&mut out)
            }
            SlotValues::Fresh => FreshSlotValues {
                old: old.slot_dim,
                new: cfg.slot_dim,
                rms_norm: old.hypernet_rms_norm,
                seed,
            }
            .apply(&mut out),
        }
        .with_context(|| format!("{name}: growing `slot_dim`"))?;
    }
    for (key, from, to) in [
        ("hypernet_hidden", old.hypernet_hidden, cfg.hypernet_hidden),
        ("lfn_hidden", old.lfn_hidden, cfg.lfn_hidden),
        ("lfn_features", old.lfn_features, cfg.lfn_features),
        ("head_hidden", old.head_hidden, cfg.head_hidden),
        (
            "head_hidden_layers",
            old.head_hidden_layers,
            cfg.head_hidden_layers,
        ),
        (
            "compositor_hidden",
            old.compositor_hidden,
            cfg.compositor_hidden,
        ),
        (
            "compositor_hidden_layers",
            old.compositor_hidden_layers,
            cfg.compositor_hidden_layers,
        ),
        (
            "floor_fourier_freqs",
            old.floor_fourier_freqs,
            cfg.floor_fourier_freqs,
        ),
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
    if cfg.hypernet_per_layer && !old.hypernet_per_layer {
        for prefix in ["hypernet_fg.", "hypernet_bg."] {
            split_hypernet_hidden(&mut out, prefix);
        }
    } else if old.hypernet_per_layer && !cfg.hypernet_per_layer {
        bail!("{name}: per-layer hypernetwork hidden layers cannot be merged back into one");
    }
    if cfg.lfn_dims() != old.lfn_dims() {
        if cfg.lfn_hidden_layers != old.lfn_hidden_layers
            || cfg.ray_fourier_freqs != old.ray_fourier_freqs
        {
            bail!("{name}: `lfn_hidden`, `lfn_features` and `floor_fourier_freqs` grow only with the same `lfn_hidden_layers` and `ray_fourier_freqs`");
        }
        // More `floor_fourier_freqs` appends input columns after all the old ones (the floor
        // columns are last, their octaves in order): zero rows, the same function.
        let grow = LayerGrowth {
            old_dims: old.lfn_dims(),
            new_dims: cfg.lfn_dims(),
            seed,
        };
        for prefix in ["hypernet_fg.", "hypernet_bg."] {
            grow.hypernet(&mut out, prefix)?;
        }
        grow.static_field(&mut out, "background_field.")?;
        if cfg.lfn_features > old.lfn_features {
            // The shadow head reads the features: zero weights on the new ones.
            grow_columns(&mut out, "heads.shadow.weight", cfg.lfn_features)?;
        }
    }
    // The heads read the light fields' features; the compositor's V reads 2 numbers a slot.
    let features = (old.lfn_features, cfg.lfn_features);
    for (prefix, input, shapes) in [
        (
            "heads.color.",
            features,
            (old.head_shape(), cfg.head_shape()),
        ),
        (
            "heads.ordering.",
            features,
            (old.head_shape(), cfg.head_shape()),
        ),
        (
            "compositor.v.",
            (2, 2),
            (old.compositor_shape(), cfg.compositor_shape()),
        ),
    ] {
        let ((old_hidden, old_layers), (hidden, layers)) = shapes;
        let growth = MlpGrowth {
            prefix,
            input,
            hidden: (old_hidden, hidden),
            hidden_layers: (old_layers, layers),
            seed,
        };
        if !growth.is_identity() {
            growth
                .apply(&mut out)
                .with_context(|| format!("{name}: growing `{prefix}`"))?;
        }
    }
    Ok(out)
}

/// Growing `slot_dim` from `old` to `new` = m·`old` values by keeping each value m times (see
/// the module's notes): value j of the grown slot is a copy of old value j mod `old`.
struct SlotGrowth {
    old: usize,
    new: usize,
    seed: u64,
}

impl SlotGrowth {
    /// How many copies each old value gets.
    fn copies(&self) -> usize {
        self.new / self.old
    }

    /// For each grown index of `blocks` stacked blocks of slot values (the GRU's three gates
    /// are three), the old index it copies.
    fn sources(&self, blocks: usize) -> Result<Tensor> {
        let index: Vec<u32> = (0..blocks * self.new)
            .map(|j| ((j / self.new) * self.old + (j % self.new) % self.old) as u32)
            .collect();
        Ok(Tensor::from_vec(index, blocks * self.new, &Device::Cpu)?)
    }

    /// A tensor whose dimension `dim` holds `blocks` blocks of slot values, each value copied.
    fn copy_values(&self, t: &Tensor, dim: usize, blocks: usize) -> Result<Tensor> {
        Ok(t.index_select(&self.sources(blocks)?, dim)?.contiguous()?)
    }

    /// A weight [out, slot] that reads a slot, each old column split evenly over its copies.
    fn split_columns(&self, t: &Tensor) -> Result<Tensor> {
        Ok((self.copy_values(t, 1, 1)? / self.copies() as f64)?)
    }

    /// As [`SlotGrowth::split_columns`], plus a seeded perturbation that sums to zero over
    /// each value's copies: N(0, (rms/m)²) draws less their mean over the copies, where rms is
    /// the old weight's.
    fn split_columns_unevenly(&self, t: &Tensor, name: &str) -> Result<Tensor> {
        let m = self.copies();
        let even = self.split_columns(t)?;
        let rows = t.dim(0)?;
        let drawn = (fresh_like(t, &[rows, m, self.old], self.seed, name)? / m as f64)?;
        let centred = drawn.broadcast_sub(&drawn.mean_keepdim(1)?)?;
        Ok((even + centred.reshape((rows, self.new))?)?.contiguous()?)
    }

    fn apply(&self, tensors: &mut BTreeMap<String, Tensor>) -> Result<()> {
        let mut update =
            |key: &str, f: &dyn Fn(&Tensor) -> Result<Tensor>| replace_tensor(tensors, key, f);
        // The projections from the image's tokens into slot space, and the background
        // reader's (a background slot read from the tokens).
        for key in [
            "slot_attention.to_k.weight",
            "slot_attention.to_v.weight",
            "background_reader.proj.weight",
            "background_reader.proj.bias",
        ] {
            update(key, &|t| self.copy_values(t, 0, 1))?;
        }
        let query_scale = 1.0 / (self.copies() as f64).sqrt();
        for branch in ["bg", "fg"] {
            let key = |part: &str| format!("slot_attention.{branch}.{part}");
            for part in [
                "mu",
                "log_sigma",
                "norm_slot.weight",
                "norm_slot.bias",
                "norm_mlp.weight",
                "norm_mlp.bias",
                "mlp.layers.1.weight",
                "mlp.layers.1.bias",
            ] {
                update(&key(part), &|t| self.copy_values(t, 0, 1))?;
            }
            update(&key("to_q.weight"), &|t| {
                Ok((self.split_columns(&self.copy_values(t, 0, 1)?)? * query_scale)?)
            })?;
            update(&key("mlp.layers.0.weight"), &|t| self.split_columns(t))?;
            // The GRU: three gates (r, z, n) of slot-sized rows; it reads the update and the
            // slot (both slot-sized) and writes the slot.
            for part in ["gru.weight_ih_l0", "gru.weight_hh_l0"] {
                update(&key(part), &|t| {
                    self.split_columns(&self.copy_values(t, 0, 3)?)
                })?;
            }
            for part in ["gru.bias_ih_l0", "gru.bias_hh_l0"] {
                update(&key(part), &|t| self.copy_values(t, 0, 3))?;
            }
        }
        // The hypernetworks read the latent: their shared hidden layer or each layer's own.
        let readers = latent_readers(tensors);
        for key in readers {
            let grown = self.split_columns_unevenly(&tensors[&key], &key)?;
            tensors.insert(key, grown);
        }
        Ok(())
    }
}

/// Growing `slot_dim` from `old` to `new` values with new values of their own (see the
/// module's notes): the new values start at zero, and the hypernetworks read them with fresh
/// weights.
struct FreshSlotValues {
    old: usize,
    new: usize,
    /// Whether the hypernetworks divide latents by their RMS (`Config::hypernet_rms_norm`).
    rms_norm: bool,
    seed: u64,
}

impl FreshSlotValues {
    /// √(old/new): what the zeros do to a norm over a slot's values (RMS, or a layer norm's
    /// deviation for slots of zero mean).
    fn norm_scale(&self) -> f64 {
        (self.old as f64 / self.new as f64).sqrt()
    }

    /// `t` with `blocks` blocks of slot values along `dim` (the GRU's gates are three), each
    /// block followed by `new − old` entries from `fill` (given the shape of one block's).
    fn extend(
        &self,
        t: &Tensor,
        dim: usize,
        blocks: usize,
        fill: &dyn Fn(&[usize]) -> Result<Tensor>,
    ) -> Result<Tensor> {
        let mut shape = t.dims().to_vec();
        shape[dim] = self.new - self.old;
        let mut parts = Vec::with_capacity(2 * blocks);
        for b in 0..blocks {
            parts.push(t.narrow(dim, b * self.old, self.old)?);
            parts.push(fill(&shape)?);
        }
        Ok(Tensor::cat(&parts, dim)?.contiguous()?)
    }

    fn zeros(shape: &[usize]) -> Result<Tensor> {
        Ok(Tensor::zeros(shape, DType::F32, &Device::Cpu)?)
    }

    fn apply(&self, tensors: &mut BTreeMap<String, Tensor>) -> Result<()> {
        let mut update =
            |key: &str, f: &dyn Fn(&Tensor) -> Result<Tensor>| replace_tensor(tensors, key, f);
        let zeros = |shape: &[usize]| Self::zeros(shape);
        // The tokens' keys and values get fresh rows: the queries' new (zero) rows and the
        // GRU's new (zero) columns then receive gradients at once.
        for key in ["slot_attention.to_k.weight", "slot_attention.to_v.weight"] {
            update(key, &|t| {
                self.extend(t, 0, 1, &|shape| fresh_like(t, shape, self.seed, key))
            })?;
        }
        // The background reader writes the background latent: zero rows keep its new values 0.
        for key in [
            "background_reader.proj.weight",
            "background_reader.proj.bias",
        ] {
            update(key, &|t| self.extend(t, 0, 1, &zeros))?;
        }
        let scale = self.norm_scale();
        for branch in ["bg", "fg"] {
            let key = |part: &str| format!("slot_attention.{branch}.{part}");
            update(&key("mu"), &|t| self.extend(t, 0, 1, &zeros))?;
            update(&key("log_sigma"), &|t| {
                self.extend(t, 0, 1, &|shape| {
                    Ok(Tensor::full(-6f32, shape, &Device::Cpu)?)
                })
            })?;
            // The zeros shrink a layer norm's deviation by √(old/new): the gains shrink with
            // it (the old units' outputs unchanged for zero-mean slots), the new ones as the
            // old ones' mean, the new biases zero.
            for norm in ["norm_slot", "norm_mlp"] {
                update(&key(&format!("{norm}.weight")), &|t| {
                    let gain = t.mean_all()?.to_scalar::<f32>()? as f64 * scale;
                    let grown = self.extend(t, 0, 1, &|shape| {
                        Ok(Tensor::full(gain as f32, shape, &Device::Cpu)?)
                    })?;
                    let old = (grown.narrow(0, 0, self.old)? * scale)?;
                    Ok(Tensor::cat(
                        &[&old, &grown.narrow(0, self.old, self.new - self.old)?],
                        0,
                    )?)
                })?;
                update(&key(&format!("{norm}.bias")), &|t| {
                    self.extend(t, 0, 1, &zeros)
                })?;
            }
            // The queries: zero new rows and columns; the old block scaled by √(new/old) for
            // the attention's 1/√D.
            update(&key("to_q.weight"), &|t| {
                let rows = self.extend(&(t / scale)?, 0, 1, &zeros)?;
                self.extend(&rows.t()?, 0, 1, &zeros)?
                    .t()?
                    .contiguous()
                    .map_err(Into::into)
            })?;
            // The residual MLP reads the normed slot (zero new columns) and writes it (zero new
            // rows).
            update(&key("mlp.layers.0.weight"), &|t| {
                Ok(self.extend(&t.t()?, 0, 1, &zeros)?.t()?.contiguous()?)
            })?;
            for part in ["mlp.layers.1.weight", "mlp.layers.1.bias"] {
                update(&key(part), &|t| self.extend(t, 0, 1, &zeros))?;
            }
            // The GRU (gates r, z, n of slot-sized rows) reads the update and the slot: zero new
            // rows (z = ½, n = 0: a new value halves each round) and zero new columns.
            for part in ["gru.weight_ih_l0", "gru.weight_hh_l0"] {
                update(&key(part), &|t| {
                    let rows = self.extend(t, 0, 3, &zeros)?;
                    Ok(self.extend(&rows.t()?, 0, 1, &zeros)?.t()?.contiguous()?)
                })?;
            }
            for part in ["gru.bias_ih_l0", "gru.bias_hh_l0"] {
                update(&key(part), &|t| self.extend(t, 0, 3, &zeros))?;
            }
        }
        // The hypernetworks read the latent: fresh columns for the new values, the old ones
        // scaled for the RMS norm's new divisor.
        let readers = latent_readers(tensors);
        let old_scale = if self.rms_norm { scale } else { 1.0 };
        for key in readers {
            let t = (&tensors[&key] * old_scale)?;
            let columns = self.extend(&t.t()?, 0, 1, &|shape| {
                fresh_like(&t, shape, self.seed, &key)
            })?;
            tensors.insert(key, columns.t()?.contiguous()?);
        }
        Ok(())
    }
}

/// `tensors[key]` replaced by `f` of it (nothing if the model has no such tensor).
fn replace_tensor(
    tensors: &mut BTreeMap<String, Tensor>,
    key: &str,
    f: &dyn Fn(&Tensor) -> Result<Tensor>,
) -> Result<()> {
    if let Some(t) = tensors.get(key) {
        let grown = f(t)?;
        tensors.insert(key.to_string(), grown);
    }
    Ok(())
}

/// The hypernetworks' weights that read a slot's latent: their shared hidden layer's or each
/// light-field layer's own.
fn latent_readers(tensors: &BTreeMap<String, Tensor>) -> Vec<String> {
    tensors
        .keys()
        .filter(|k| {
            (k.starts_with("hypernet_fg.") || k.starts_with("hypernet_bg."))
                && k.ends_with("fc1.weight")
        })
        .cloned()
        .collect()
}

/// `{key}` [rows, C] widened to `columns` with zero columns: new inputs have no effect yet.
fn grow_columns(tensors: &mut BTreeMap<String, Tensor>, key: &str, columns: usize) -> Result<()> {
    let Some(t) = tensors.get(key).cloned() else {
        return Ok(());
    };
    let (rows, old) = t.dims2()?;
    let zeros = Tensor::zeros((rows, columns - old), DType::F32, &Device::Cpu)?;
    tensors.insert(
        key.to_string(),
        Tensor::cat(&[&t, &zeros], 1)?.contiguous()?,
    );
    Ok(())
}

/// Growing an [`Mlp`](super::layers::Mlp) of ReLU layers (`{prefix}layers.{i}.weight` [out,
/// in], `.bias` [out]) while it computes the same function: `(old, new)` input width, hidden
/// width and number of hidden layers.
/// - Wider input: zero weights on the new inputs (they have no effect yet).
/// - Wider hidden layers: the new units get fresh incoming weights and biases, and zero
///   weights into every old unit and into the output.
/// - More hidden layers: inserted before the output layer as the identity on the old units
///   (exact after a ReLU, whose outputs are ≥ 0), their new units fresh, as above.
struct MlpGrowth<'a> {
    prefix: &'a str,
    input: (usize, usize),
    hidden: (usize, usize),
    hidden_layers: (usize, usize),
    seed: u64,
}

impl MlpGrowth<'_> {
    fn is_identity(&self) -> bool {
        self.input.0 == self.input.1
            && self.hidden.0 == self.hidden.1
            && self.hidden_layers.0 == self.hidden_layers.1
    }

    fn apply(&self, tensors: &mut BTreeMap<String, Tensor>) -> Result<()> {
        let (old_layers, new_layers) = self.hidden_layers;
        if old_layers == 0 && new_layers > 0 {
            bail!("a linear output layer cannot gain hidden layers while keeping its function");
        }
        let key = |i: usize, part: &str| format!("{}layers.{i}.{part}", self.prefix);
        if !tensors.contains_key(&key(0, "weight")) {
            return Ok(());
        }
        // The output layer moves to its new index; read it before anything is overwritten.
        let output_weight = tensors
            .remove(&key(old_layers, "weight"))
            .with_context(|| format!("no tensor `{}`", key(old_layers, "weight")))?;
        let output_bias = tensors.remove(&key(old_layers, "bias"));
        let width = |i: usize, new: bool| match (i, new) {
            (0, false) => self.input.0,
            (0, true) => self.input.1,
            (_, false) => self.hidden.0,
            (_, true) => self.hidden.1,
        };
        for i in 0..old_layers {
            let (weight_key, bias_key) = (key(i, "weight"), key(i, "bias"));
            let weight = tensors[&weight_key].clone();
            let bias = tensors[&bias_key].clone();
            let (weight, bias) = self.widen(&weight, &bias, width(i, true), &weight_key)?;
            tensors.insert(weight_key, weight);
            tensors.insert(bias_key, bias);
        }
        // Fresh units in the inserted layers are drawn like the last old hidden layer's.
        let last_weight = tensors[&key(old_layers - 1, "weight")].clone();
        let last_bias = tensors[&key(old_layers - 1, "bias")].clone();
        let (old_hidden, hidden) = self.hidden;
        for i in old_layers..new_layers {
            let (weight_key, bias_key) = (key(i, "weight"), key(i, "bias"));
            let identity = Tensor::eye(old_hidden, DType::F32, &Device::Cpu)?;
            let identity_bias = Tensor::zeros(old_hidden, DType::F32, &Device::Cpu)?;
            let (mut weight, mut bias) = (identity, identity_bias);
            if hidden > old_hidden {
                // Widen the identity like an old layer: same rule for its new units.
                let rows = fresh_like(
                    &last_weight,
                    &[hidden - old_hidden, hidden],
                    self.seed,
                    &weight_key,
                )?;
                let zeros =
                    Tensor::zeros((old_hidden, hidden - old_hidden), DType::F32, &Device::Cpu)?;
                weight = Tensor::cat(&[&Tensor::cat(&[&weight, &zeros], 1)?, &rows], 0)?;
                let fresh = fresh_like(&last_bias, &[hidden - old_hidden], self.seed, &bias_key)?;
                bias = Tensor::cat(&[&bias, &fresh], 0)?;
            }
            tensors.insert(weight_key, weight.contiguous()?);
            tensors.insert(bias_key, bias);
        }
        // The output layer reads only the old units: zero weights on the new ones.
        let (outputs, old_in) = output_weight.dims2()?;
        let new_in = width(new_layers, true);
        let mut weight = output_weight;
        if new_in > old_in {
            let zeros = Tensor::zeros((outputs, new_in - old_in), DType::F32, &Device::Cpu)?;
            weight = Tensor::cat(&[&weight, &zeros], 1)?.contiguous()?;
        }
        tensors.insert(key(new_layers, "weight"), weight);
        if let Some(bias) = output_bias {
            tensors.insert(key(new_layers, "bias"), bias);
        }
        Ok(())
    }

    /// A hidden layer's weight [out, in] and bias [out] grown to `new_in` inputs (zero columns)
    /// and the new hidden width (fresh rows and bias entries, drawn like their neighbours).
    fn widen(
        &self,
        weight: &Tensor,
        bias: &Tensor,
        new_in: usize,
        name: &str,
    ) -> Result<(Tensor, Tensor)> {
        let (old_out, old_in) = weight.dims2()?;
        let new_out = self.hidden.1;
        let mut grown = weight.clone();
        if new_in > old_in {
            let zeros = Tensor::zeros((old_out, new_in - old_in), DType::F32, &Device::Cpu)?;
            grown = Tensor::cat(&[&grown, &zeros], 1)?;
        }
        let mut bias = bias.clone();
        if new_out > old_out {
            let rows = fresh_like(weight, &[new_out - old_out, new_in], self.seed, name)?;
            grown = Tensor::cat(&[&grown, &rows], 0)?;
            let fresh = fresh_like(
                &bias,
                &[new_out - old_out],
                self.seed,
                &format!("{name}:bias"),
            )?;
            bias = Tensor::cat(&[&bias, &fresh], 0)?;
        }
        Ok((grown.contiguous()?, bias))
    }
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

/// Widens the hidden layers of the hypernetwork under `prefix` (if present) to `hidden` units:
/// its shared `fc1`, or each layer's own (`Config::hypernet_per_layer`).
fn widen_hypernet(
    tensors: &mut BTreeMap<String, Tensor>,
    prefix: &str,
    hidden: usize,
    seed: u64,
) -> Result<()> {
    if tensors.contains_key(&format!("{prefix}fc1.weight")) {
        return widen_hidden(tensors, &format!("{prefix}fc1."), prefix, hidden, seed);
    }
    let mut l = 0;
    while tensors.contains_key(&format!("{prefix}layers.{l}.fc1.weight")) {
        let layer = format!("{prefix}layers.{l}.");
        widen_hidden(tensors, &format!("{layer}fc1."), &layer, hidden, seed)?;
        l += 1;
    }
    Ok(())
}

/// Widens the hidden layer `fc1` (`{fc1}weight`, `{fc1}bias`) to `hidden` units: fresh input
/// weights for the new units, and zero columns for them in every head under `heads`.
fn widen_hidden(
    tensors: &mut BTreeMap<String, Tensor>,
    fc1: &str,
    heads: &str,
    hidden: usize,
    seed: u64,
) -> Result<()> {
    let (fc1_weight, fc1_bias) = (format!("{fc1}weight"), format!("{fc1}bias"));
    let weight = tensors[&fc1_weight].clone();
    let (old_hidden, inputs) = weight.dims2()?;
    let extra = hidden - old_hidden;
    let new_rows = fresh_like(&weight, &[extra, inputs], seed, &fc1_weight)?;
    tensors.insert(fc1_weight, Tensor::cat(&[&weight, &new_rows], 0)?);
    let bias = tensors[&fc1_bias].clone();
    let new_bias = fresh_like(&bias, &[extra], seed, &fc1_bias)?;
    tensors.insert(fc1_bias, Tensor::cat(&[&bias, &new_bias], 0)?);
    for key in head_names(tensors, heads) {
        if key.ends_with(".weight") {
            let head = tensors[&key].clone();
            let zeros = Tensor::zeros((head.dim(0)?, extra), DType::F32, &Device::Cpu)?;
            tensors.insert(key, Tensor::cat(&[&head, &zeros], 1)?.contiguous()?);
        }
    }
    Ok(())
}

/// Gives each light-field layer of the hypernetwork under `prefix` (if present) its own copy
/// of the shared hidden layer (`Config::hypernet_per_layer`): the same light fields at first,
/// then each layer's hidden units free to learn their own directions.
fn split_hypernet_hidden(tensors: &mut BTreeMap<String, Tensor>, prefix: &str) {
    let shared = format!("{prefix}fc1.");
    let (Some(weight), Some(bias)) = (
        tensors.remove(&format!("{shared}weight")),
        tensors.remove(&format!("{shared}bias")),
    ) else {
        return;
    };
    let mut l = 0;
    while tensors.contains_key(&format!("{prefix}layers.{l}.weight.weight")) {
        tensors.insert(format!("{prefix}layers.{l}.fc1.weight"), weight.clone());
        tensors.insert(format!("{prefix}layers.{l}.fc1.bias"), bias.clone());
        l += 1;
    }
}

/// The names of the heads under `prefix` (a hypernetwork's, or one layer's):
/// `…layers.{l}.{weight,bias}.{weight,bias}`, not the per-layer hidden layers (`…fc1.`).
fn head_names(tensors: &BTreeMap<String, Tensor>, prefix: &str) -> Vec<String> {
    tensors
        .keys()
        .filter(|k| {
            k.strip_prefix(prefix)
                .is_some_and(|rest| !rest.contains("fc1."))
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
