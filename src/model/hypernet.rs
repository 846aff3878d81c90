//! Hypernetworks: a slot latent → every weight and bias of that slot's light-field MLP
//! (COLF supplement §1.2: an MLP with one hidden layer). Foreground and background have separate
//! hypernetworks.
//!
//! Structure: `fc1` (D → H, ReLU) shared by all outputs, then for each light-field layer l with
//! fan-in `i` and fan-out `o` two linear heads: `layers.{l}.weight` (H → i·o, reshaped to the
//! layer's [i, o] weight, laid out for `x [S, R, i] · W [S, i, o]`) and `layers.{l}.bias`
//! (H → o). Tensor names (prefix `hypernet_fg.` / `hypernet_bg.`): `fc1.{weight,bias}`,
//! `layers.{l}.weight.{weight,bias}`, `layers.{l}.bias.{weight,bias}`.
//!
//! With `Config::hypernet_per_layer`, each layer's two heads read a hidden layer of their own,
//! `layers.{l}.fc1.{weight,bias}` (D → H, ReLU), in place of the shared `fc1`: every generated
//! weight is still an affine function of H hidden units, but each layer has its own H, so the
//! light fields a hypernetwork can make span L·H dimensions (SIREN's and LFN's hypernetworks
//! give each generated tensor its own MLP).
//!
//! Initialisation: the generated weights should have a Kaiming-like scale whatever the latent.
//! Each generated weight is `A·h + c`; `c` (the head's bias) is drawn uniformly with variance
//! ¾·σ², and `A` uniformly so that `A·h` has variance ¼·σ² for hidden activations h of a
//! unit-variance latent (E[h²] ≈ 1/6 after fc1's default init and the ReLU), where
//! σ = gain/√fan_in is the Kaiming std of that layer (gain √2 before a ReLU, 1 on the last).

use super::config::Config;
use super::fused::{self, Activation};
use candle_core::{Result, Tensor};
use candle_nn::{linear, Init, Linear, VarBuilder};

/// One light-field layer's generated parameters for S slots: weight [S, in, out], bias
/// [S, 1, out].
#[derive(Clone, Debug)]
pub struct GeneratedLayer {
    pub weight: Tensor,
    pub bias: Tensor,
}

#[derive(Clone, Debug)]
struct LayerHeads {
    weight: Linear,
    bias: Linear,
    fan_in: usize,
    fan_out: usize,
}

/// `layer` applied to x [S, in] as one fused op (the heads hold most of a model's weights, and
/// their gradients are made in place; see [`fused::linear`]).
fn linear_layer(x: &Tensor, layer: &Linear, act: Activation) -> Result<Tensor> {
    match layer.bias() {
        Some(bias) => fused::linear(x, layer.weight(), bias, act),
        None => candle_core::bail!("hypernetwork layers have biases"),
    }
}

/// A hypernetwork for light fields of widths `cfg.lfn_dims()`.
#[derive(Clone, Debug)]
pub struct HyperNet {
    /// The hidden layers: one shared by every layer's heads, or one per light-field layer
    /// (`Config::hypernet_per_layer`).
    fc1: Vec<Linear>,
    layers: Vec<LayerHeads>,
    /// See `Config::hypernet_rms_norm`.
    rms_norm: bool,
}

/// Kaiming std of light-field layer `l` of widths `dims`: gain/√fan_in, gain √2 before a ReLU
/// and 1 on the last layer.
fn kaiming_std(dims: &[usize], l: usize) -> f64 {
    let gain = if l + 2 == dims.len() {
        1.0
    } else {
        2f64.sqrt()
    };
    gain / (dims[l] as f64).sqrt()
}

fn head(inp: usize, out: usize, a: f64, c: f64, vb: VarBuilder) -> Result<Linear> {
    let weight = vb.get_with_hints((out, inp), "weight", Init::Uniform { lo: -a, up: a })?;
    let bias = vb.get_with_hints(out, "bias", Init::Uniform { lo: -c, up: c })?;
    Ok(Linear::new(weight, Some(bias)))
}

impl HyperNet {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<HyperNet> {
        let h = cfg.hypernet_hidden;
        let dims = cfg.lfn_dims();
        let fc1 = if cfg.hypernet_per_layer {
            (0..dims.len() - 1)
                .map(|l| linear(cfg.slot_dim, h, vb.pp(format!("layers.{l}.fc1"))))
                .collect::<Result<_>>()?
        } else {
            vec![linear(cfg.slot_dim, h, vb.pp("fc1"))?]
        };
        let mut layers = Vec::new();
        for l in 0..dims.len() - 1 {
            let (fan_in, fan_out) = (dims[l], dims[l + 1]);
            let sigma = kaiming_std(&dims, l);
            // Var(A·h) = H·a²/3·E[h²] with E[h²] ≈ 1/6 → a = √(4.5/H)·σ gives ¼σ².
            let a = (4.5 / h as f64).sqrt() * sigma;
            // Var(U(−c, c)) = c²/3 = ¾σ² → c = 1.5σ.
            let c = 1.5 * sigma;
            let vb_l = vb.pp(format!("layers.{l}"));
            layers.push(LayerHeads {
                weight: head(h, fan_in * fan_out, a, c, vb_l.pp("weight"))?,
                // Generated biases: small, latent-dependent, around zero.
                bias: head(
                    h,
                    fan_out,
                    0.5 * a,
                    0.5 / (fan_in as f64).sqrt(),
                    vb_l.pp("bias"),
                )?,
                fan_in,
                fan_out,
            });
        }
        Ok(HyperNet {
            fc1,
            layers,
            rms_norm: cfg.hypernet_rms_norm,
        })
    }

    /// latents [S, D] → the S light fields' layers.
    pub fn forward(&self, latents: &Tensor) -> Result<Vec<GeneratedLayer>> {
        let hidden = self.hidden_layers(latents)?;
        (0..self.layers.len())
            // One shared hidden layer, or layer l's own.
            .map(|l| self.generate(l, &hidden[l % hidden.len()]))
            .collect()
    }

    /// latents [S, D] → the hidden layers' activations [S, H], or [S, L·H] with one hidden
    /// layer per light-field layer (layer l's in columns l·H…). Every generated weight is an
    /// affine function of these: the S light fields lie in an H- (or L·H-) dimensional affine
    /// subspace of the light field's weights (`examples/capacity_fit` measures what that
    /// costs).
    pub fn hidden(&self, latents: &Tensor) -> Result<Tensor> {
        Tensor::cat(&self.hidden_layers(latents)?, 1)
    }

    /// The hidden activations ([`HyperNet::hidden`]'s shape) → the S light fields' layers.
    pub fn from_hidden(&self, hidden: &Tensor) -> Result<Vec<GeneratedLayer>> {
        let width = hidden.dim(1)? / self.fc1.len();
        (0..self.layers.len())
            .map(|l| {
                let own = if self.fc1.len() == 1 {
                    hidden.clone()
                } else {
                    hidden.narrow(1, l * width, width)?.contiguous()?
                };
                self.generate(l, &own)
            })
            .collect()
    }

    /// latents [S, D] → each hidden layer's activations [S, H] (one, or one per light-field
    /// layer).
    fn hidden_layers(&self, latents: &Tensor) -> Result<Vec<Tensor>> {
        let latents = self.normalized(latents)?;
        self.fc1
            .iter()
            .map(|fc1| linear_layer(&latents, fc1, Activation::Relu))
            .collect()
    }

    /// latents [S, D] as the hidden layers read them: divided by their root-mean-square when
    /// `Config::hypernet_rms_norm` is set, else as they are.
    pub fn normalized(&self, latents: &Tensor) -> Result<Tensor> {
        if !self.rms_norm {
            return Ok(latents.clone());
        }
        let rms = (latents.sqr()?.mean_keepdim(1)? + 1e-6)?.sqrt()?;
        latents.broadcast_div(&rms)
    }

    /// Whether [`HyperNet::normalized`] divides by the latents' root-mean-square.
    pub fn rms_norm(&self) -> bool {
        self.rms_norm
    }

    /// The hidden layers' weights [H, D] and biases [H] (one, or one per light-field layer):
    /// what maps a latent to the hidden activations, for studies of that map
    /// (`examples/capacity_fit --wide-latents`).
    pub fn hidden_layer_weights(&self) -> Vec<(Tensor, Tensor)> {
        self.fc1
            .iter()
            .map(|fc1| {
                let bias = fc1.bias().expect("hypernetwork layers have biases").clone();
                (fc1.weight().clone(), bias)
            })
            .collect()
    }

    /// Light-field layer `l`'s weights and biases from the hidden activations its heads read.
    fn generate(&self, l: usize, hidden: &Tensor) -> Result<GeneratedLayer> {
        let (s, heads) = (hidden.dim(0)?, &self.layers[l]);
        Ok(GeneratedLayer {
            weight: linear_layer(hidden, &heads.weight, Activation::Identity)?.reshape((
                s,
                heads.fan_in,
                heads.fan_out,
            ))?,
            bias: linear_layer(hidden, &heads.bias, Activation::Identity)?.reshape((
                s,
                1,
                heads.fan_out,
            ))?,
        })
    }
}

/// The background light field of a `static_background` model: its weights are parameters,
/// initialised like a hypernetwork's output at a typical latent (Kaiming scale). Tensor names
/// (prefix `background_field.`): `layers.{l}.weight` [in, out] and `layers.{l}.bias` [out].
#[derive(Clone, Debug)]
pub struct StaticField {
    layers: Vec<(Tensor, Tensor)>,
}

impl StaticField {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<StaticField> {
        let dims = cfg.lfn_dims();
        let mut layers = Vec::new();
        for l in 0..dims.len() - 1 {
            let (fan_in, fan_out) = (dims[l], dims[l + 1]);
            // Uniform with the Kaiming variance σ²: bound √3·σ.
            let bound = 3f64.sqrt() * kaiming_std(&dims, l);
            let vb_l = vb.pp(format!("layers.{l}"));
            let weight = vb_l.get_with_hints(
                (fan_in, fan_out),
                "weight",
                Init::Uniform {
                    lo: -bound,
                    up: bound,
                },
            )?;
            let bias = vb_l.get_with_hints(fan_out, "bias", Init::Const(0.0))?;
            layers.push((weight, bias));
        }
        Ok(StaticField { layers })
    }

    /// The same light field for each of `count` scenes.
    pub fn forward(&self, count: usize) -> Result<Vec<GeneratedLayer>> {
        self.layers
            .iter()
            .map(|(weight, bias)| {
                let (i, o) = weight.dims2()?;
                Ok(GeneratedLayer {
                    weight: weight
                        .unsqueeze(0)?
                        .broadcast_as((count, i, o))?
                        .contiguous()?,
                    bias: bias
                        .reshape((1, 1, o))?
                        .broadcast_as((count, 1, o))?
                        .contiguous()?,
                })
            })
            .collect()
    }
}

/// Where the background slot's light field comes from.
#[derive(Clone, Debug)]
pub enum BackgroundField {
    /// A hypernetwork of the background latent (`hypernet_bg.`).
    HyperNet(HyperNet),
    /// Fixed weights (`background_field.`; `Config::static_background`).
    Static(StaticField),
}

impl BackgroundField {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<BackgroundField> {
        Ok(if cfg.static_background {
            BackgroundField::Static(StaticField::new(cfg, vb.pp("background_field"))?)
        } else {
            BackgroundField::HyperNet(HyperNet::new(cfg, vb.pp("hypernet_bg"))?)
        })
    }

    /// latents [B, D] → the B background light fields.
    pub fn forward(&self, latents: &Tensor) -> Result<Vec<GeneratedLayer>> {
        match self {
            BackgroundField::HyperNet(h) => h.forward(latents),
            BackgroundField::Static(s) => s.forward(latents.dim(0)?),
        }
    }
}
