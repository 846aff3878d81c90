//! A trained model's weights under a config that changes its shape in ways that keep what it
//! computes, so training can continue from it (`colf-train --init M --set …`):
//! - `static_background` on a zero-background model: the background hypernetwork's output at
//!   the zero latent — the only light field it ever produced — becomes the background field's
//!   weights (`background_field.`), and `hypernet_bg.` is dropped;
//! - a wider `hypernet_hidden`: each hypernetwork's new hidden units get fresh input weights
//!   (drawn like the existing ones, seeded by (seed, tensor name)) and zero output weights, so
//!   every generated light field is unchanged until training moves them — and it can, since the
//!   new units are active and their output weights receive gradients.
//!
//! Anything else must keep every tensor's name and shape; `Colf::reconfigured` checks that.

use super::config::Config;
use super::hypernet::BackgroundField;
use super::init::tensor_seed;
use super::ColfModel;
use anyhow::{bail, Result};
use candle_core::{DType, Device, Tensor};
use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::collections::BTreeMap;

/// `model`'s tensors (`tensors`) grown and converted for `cfg`; `name` is used in errors.
pub fn grow_tensors(
    model: &ColfModel,
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
            bail!("{name}: `static_background` needs a model trained with a zero background latent; this one's background depends on the image");
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
    if cfg.hypernet_hidden != old.hypernet_hidden {
        if cfg.hypernet_hidden < old.hypernet_hidden {
            bail!(
                "{name}: `hypernet_hidden` can grow ({} → more), not shrink",
                old.hypernet_hidden
            );
        }
        for prefix in ["hypernet_fg.", "hypernet_bg."] {
            widen_hypernet(&mut out, prefix, cfg.hypernet_hidden, seed)?;
        }
    }
    Ok(out)
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
    let fresh = |name: &str, like: &Tensor, shape: &[usize]| -> Result<Tensor> {
        let values = like.flatten_all()?.to_vec1::<f32>()?;
        let std = (values.iter().map(|v| v * v).sum::<f32>() / values.len().max(1) as f32).sqrt();
        let normal = Normal::new(0.0, std.max(1e-6))?;
        let mut rng = StdRng::seed_from_u64(tensor_seed(seed, &format!("grow:{name}")));
        let n = shape.iter().product();
        let drawn: Vec<f32> = (0..n).map(|_| normal.sample(&mut rng)).collect();
        Ok(Tensor::from_vec(drawn, shape, &Device::Cpu)?)
    };
    let new_rows = fresh(&fc1_weight, &weight, &[extra, inputs])?;
    tensors.insert(fc1_weight.clone(), Tensor::cat(&[&weight, &new_rows], 0)?);
    let bias = tensors[&fc1_bias].clone();
    let new_bias = fresh(&fc1_bias, &bias, &[extra])?;
    tensors.insert(fc1_bias, Tensor::cat(&[&bias, &new_bias], 0)?);
    // Every head reads the hidden layer: zero columns for the new units.
    let heads: Vec<String> = tensors
        .keys()
        .filter(|k| {
            k.strip_prefix(prefix).is_some_and(|rest| {
                rest.starts_with("layers.")
                    && (rest.ends_with(".weight.weight") || rest.ends_with(".bias.weight"))
            })
        })
        .cloned()
        .collect();
    for key in heads {
        let head = tensors[&key].clone();
        let rows = head.dim(0)?;
        let zeros = Tensor::zeros((rows, extra), DType::F32, &Device::Cpu)?;
        tensors.insert(key, Tensor::cat(&[&head, &zeros], 1)?.contiguous()?);
    }
    Ok(())
}
