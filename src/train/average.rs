//! Weight averaging: the mean of several models of one run (e.g. the snapshots `colf-train
//! --keep-every` kept while the learning rate is still high), a cheap ensemble that keeps the
//! cost of one model. Only models with the same config and the same tensors can be averaged.

use crate::model::checkpoint::{self, HostParams};
use crate::model::Colf;
use anyhow::{bail, Result};

/// The element-wise mean of the parameters of `models` (each with the name errors give it), as
/// a model file's bytes and its identity.
pub fn average(models: &[(&str, &Colf)]) -> Result<(Vec<u8>, String)> {
    let Some(&(first_name, first)) = models.first() else {
        bail!("nothing to average: give at least one model");
    };
    let config = first.config().to_json();
    let mut sum: BTreeSum = BTreeSum::new();
    for &(name, model) in models {
        if model.config().to_json() != config {
            bail!("{name}: its config differs from {first_name}'s");
        }
        // One config means the same tensors with the same shapes: a model file is checked
        // against the model its config describes when it is loaded.
        for (tensor, (shape, data)) in checkpoint::to_host(model.parameters())? {
            let (_, acc) = sum
                .entry(tensor)
                .or_insert_with(|| (shape, vec![0.0; data.len()]));
            for (a, v) in acc.iter_mut().zip(data) {
                *a += v as f64;
            }
        }
    }
    let n = models.len() as f64;
    let mean: HostParams = sum
        .into_iter()
        .map(|(tensor, (shape, acc))| {
            (
                tensor,
                (shape, acc.iter().map(|a| (a / n) as f32).collect()),
            )
        })
        .collect();
    // Models of one run share its records; the first model's are kept. The mean is written in
    // f32 whatever the inputs' storage.
    Ok(checkpoint::to_bytes(
        first.config(),
        &mean,
        first.training(),
        &Default::default(),
    ))
}

/// Sums in f64, so the mean of many snapshots loses no precision.
type BTreeSum = std::collections::BTreeMap<String, (Vec<usize>, Vec<f64>)>;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Config;

    fn model(seed: u64) -> Colf {
        Colf::init(&Config::small(), seed).unwrap()
    }

    #[test]
    fn the_average_is_the_elementwise_mean() {
        let (a, b) = (model(1), model(2));
        let (bytes, _) = average(&[("a", &a), ("b", &b)]).unwrap();
        let mean = Colf::from_bytes(&bytes, "mean").unwrap();
        for (tensor, value) in mean.parameters() {
            let got = value.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let va = a.parameters()[tensor]
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            let vb = b.parameters()[tensor]
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            for ((g, x), y) in got.iter().zip(&va).zip(&vb) {
                assert!((g - (x + y) / 2.0).abs() <= 1e-6 * (1.0 + x.abs() + y.abs()));
            }
        }
        // The mean of one model is that model, byte for byte.
        let (one, id) = average(&[("a", &a)]).unwrap();
        assert_eq!(one, a.to_bytes().unwrap().0);
        assert_eq!(id, a.identity().unwrap());
    }

    #[test]
    fn models_of_different_configs_are_refused() {
        let mut cfg = Config::small();
        cfg.lfn_hidden += 8;
        let other = Colf::init(&cfg, 1).unwrap();
        let err = average(&[("a.safetensors", &model(1)), ("b.safetensors", &other)])
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("b.safetensors: its config differs"),
            "{err}"
        );
        assert!(average(&[]).is_err());
    }
}
