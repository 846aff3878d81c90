//! The background reader (`Config::background_reader`): the background slot's latent read from
//! the whole image rather than from slot attention.
//!
//! A model trained with a zero background latent draws one floor for every image; turned into
//! an image-dependent one, its slot-attention background latent barely varies between images
//! (measured on the `blender` adaptation: norm 133, 0.42 per dimension across scenes), so the
//! background still cannot follow a scene's floor or light. The mean of the encoder's tokens
//! always carries them. Tensor names (prefix `background_reader.`): `proj.{weight,bias}`
//! ([D, C], [D]), C = `feature_dim` (the encoder's token size), D = `slot_dim`.

use super::Config;
use candle_core::{Module, Result, Tensor};
use candle_nn::{linear, Linear, VarBuilder};

/// Mean of the tokens → a linear map to the slot size. No normalisation here: the
/// hypernetwork divides each latent by its root-mean-square (`hypernet_rms_norm`), and a norm
/// over the pooled features would remove their overall scale, which is where a brighter image
/// shows.
#[derive(Clone, Debug)]
pub struct BackgroundReader {
    proj: Linear,
}

impl BackgroundReader {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<BackgroundReader> {
        Ok(BackgroundReader {
            proj: linear(cfg.feature_dim, cfg.slot_dim, vb.pp("proj"))?,
        })
    }

    /// tokens [B, N, C] → background latents [B, D]: the tokens' mean, projected.
    pub fn forward(&self, tokens: &Tensor) -> Result<Tensor> {
        self.proj.forward(&tokens.mean(1)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use candle_nn::VarMap;

    fn max_abs(t: &Tensor) -> f32 {
        t.abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }

    /// A fresh reader for tokens of `feature_dim` values, its parameters in the returned map.
    fn fresh_reader(feature_dim: usize) -> (VarMap, Config, BackgroundReader) {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let cfg = Config {
            feature_dim,
            ..Config::small()
        };
        let reader = BackgroundReader::new(&cfg, vb.pp("background_reader")).unwrap();
        (varmap, cfg, reader)
    }

    #[test]
    fn reads_the_mean_token_whatever_the_order_and_count() {
        let (varmap, cfg, reader) = fresh_reader(8);
        let mut names: Vec<String> = varmap.data().lock().unwrap().keys().cloned().collect();
        names.sort();
        assert_eq!(
            names,
            [
                "background_reader.proj.bias",
                "background_reader.proj.weight"
            ]
        );
        let tokens = Tensor::randn(0f32, 1.0, (2, 6, 8), &Device::Cpu).unwrap();
        let out = reader.forward(&tokens).unwrap();
        assert_eq!(out.dims(), &[2, cfg.slot_dim]);
        // The same tokens in another order, then all of them again: the same latent.
        let reordered = Tensor::cat(
            &[
                &tokens.narrow(1, 3, 3).unwrap(),
                &tokens.narrow(1, 0, 3).unwrap(),
            ],
            1,
        )
        .unwrap();
        let doubled = Tensor::cat(&[&reordered, &tokens], 1).unwrap();
        let diff = (reader.forward(&doubled).unwrap() - &out).unwrap();
        assert!(max_abs(&diff) < 1e-5);
    }

    #[test]
    fn a_brighter_image_moves_the_latent_and_the_gradient_reaches_the_map() {
        let (varmap, _, reader) = fresh_reader(4);
        let tokens = Tensor::rand(0f32, 1.0, (1, 5, 4), &Device::Cpu).unwrap();
        let dim = reader.forward(&tokens).unwrap();
        let bright = reader.forward(&(&tokens * 2.0).unwrap()).unwrap();
        assert!(max_abs(&(&bright - &dim).unwrap()) > 1e-3);
        let grads = bright.sum_all().unwrap().backward().unwrap();
        let data = varmap.data().lock().unwrap();
        let weight = data.get("background_reader.proj.weight").unwrap();
        let grad = grads
            .get(weight.as_tensor())
            .expect("a gradient for proj.weight");
        assert!(max_abs(grad) > 0.0);
    }
}
