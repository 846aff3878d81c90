//! The COLF model in candle: encoder → background-aware slot attention → per-slot hypernetwork
//! light fields → colour/ordering heads → compositor. See `docs/model.md` for the tensor names,
//! the checkpoint format and the design choices.
//!
//! Two levels:
//! - [`ColfModel`]: the module tree on tensors (differentiable; used by training).
//! - [`Colf`]: a loaded model with the host-side API that `colf-encode`/`colf-render` use:
//!   [`Colf::encode`] an image into slot latents, [`Colf::prepare`] slots (hypernetworks run
//!   once per slot) and [`Colf::render_rays`] any number of world rays in bounded-memory chunks.

pub mod checkpoint;
pub mod compositor;
pub mod config;
pub mod conv;
pub mod encoder;
pub mod frames;
pub mod fused;
pub mod grow;
pub mod heads;
pub mod hypernet;
pub mod init;
pub mod layers;
pub mod light_field;
pub mod rays;
pub mod slot_attention;
pub mod volumetric;

pub use config::Config;
pub use light_field::SlotWeights;
pub use rays::{RayBatch, SceneRays};
pub use slot_attention::SlotOutput;

use anyhow::{anyhow, bail, Context, Result};
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use glam::{DMat4, DVec3};
use rand::rngs::StdRng;
use rand::SeedableRng;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The differentiable model. Parameters live under `encoder.`, `slot_attention.` and the
/// decoder's prefixes: `hypernet_fg.`, `hypernet_bg.` (or `background_field.`), `heads.` and
/// `compositor.` for light
/// fields, `volumetric.` for the volumetric baseline (`Config::volumetric`).
#[derive(Clone, Debug)]
pub struct ColfModel {
    pub cfg: Config,
    pub encoder: encoder::Encoder,
    pub slot_attention: slot_attention::SlotAttention,
    pub decoder: Decoder,
}

/// How slots become pixels.
#[derive(Clone, Debug)]
pub enum Decoder {
    /// COLF: per-slot light fields from hypernetworks, heads and the compositor.
    LightField(Box<LightFieldDecoder>),
    /// The uORF-style volumetric baseline (inference only; see `volumetric.rs`).
    Volumetric(Box<volumetric::Volumetric>),
}

/// The light-field decoder's modules.
#[derive(Clone, Debug)]
pub struct LightFieldDecoder {
    pub hypernet_fg: hypernet::HyperNet,
    pub background: hypernet::BackgroundField,
    pub heads: heads::Heads,
    pub compositor: compositor::Compositor,
}

/// What [`ColfModel::decode`] returns.
#[derive(Clone, Debug)]
pub struct Decoded {
    /// Composited colour [B, R, 3].
    pub rgb: Tensor,
    /// Compositor weights [B, R, S], S = 1 + K, index 0 = background.
    pub weights: Tensor,
    /// log of `weights`, by log-softmax (use for losses on the weights) [B, R, S].
    pub log_weights: Tensor,
    /// Each field's colour [B, R, S, 3]; the background's already darkened by the shadows.
    pub colors: Tensor,
    /// World-comparable ordering values minus the per-ray `RayBatch::base` [B, R, S].
    pub ordering: Tensor,
    /// Each field's shadow density σ [B, R, S] (0 for the background), with a shadow head.
    pub shadow: Option<Tensor>,
}

/// A light-field model's decoder modules read as fields of the model (`model.heads`,
/// `model.hypernet_fg`, …), as before the volumetric baseline existed.
///
/// # Panics
/// On a volumetric model, which has none of them: code that handles any model uses
/// [`ColfModel::light_field`], and [`ColfModel::prepare`] / [`ColfModel::decode`] return errors.
impl std::ops::Deref for ColfModel {
    type Target = LightFieldDecoder;
    fn deref(&self) -> &LightFieldDecoder {
        self.light_field()
            .expect("a light-field model (this one is volumetric)")
    }
}

impl ColfModel {
    pub fn new(cfg: &Config, vb: VarBuilder) -> candle_core::Result<ColfModel> {
        let encoder = encoder::Encoder::new(cfg, vb.pp("encoder"))?;
        let slot_attention = slot_attention::SlotAttention::new(cfg, vb.pp("slot_attention"))?;
        let decoder = if cfg.is_volumetric() {
            Decoder::Volumetric(Box::new(volumetric::Volumetric::new(
                cfg,
                vb.pp("volumetric"),
            )?))
        } else {
            Decoder::LightField(Box::new(LightFieldDecoder {
                hypernet_fg: hypernet::HyperNet::new(cfg, vb.pp("hypernet_fg"))?,
                background: hypernet::BackgroundField::new(cfg, vb.clone())?,
                heads: heads::Heads::new(cfg, vb.pp("heads"))?,
                compositor: compositor::Compositor::new(cfg, vb.pp("compositor"))?,
            }))
        };
        Ok(ColfModel {
            cfg: cfg.clone(),
            encoder,
            slot_attention,
            decoder,
        })
    }

    /// The light-field decoder (None for a volumetric model).
    pub fn light_field(&self) -> Option<&LightFieldDecoder> {
        match &self.decoder {
            Decoder::LightField(lf) => Some(lf),
            Decoder::Volumetric(_) => None,
        }
    }

    /// The volumetric decoder (None for a light-field model).
    pub fn volumetric(&self) -> Option<&volumetric::Volumetric> {
        match &self.decoder {
            Decoder::Volumetric(v) => Some(v),
            Decoder::LightField(_) => None,
        }
    }

    fn light_field_or_err(&self) -> candle_core::Result<&LightFieldDecoder> {
        self.light_field().ok_or_else(|| {
            candle_core::Error::Msg(
                "this is a volumetric (baseline) model: it renders, but light-field training and decoding do not apply".into(),
            )
        })
    }

    /// images [B, 3, S, S] (S = `encoder_size`, values in [0, 1]) → K foreground slots and the
    /// background slot; the slot noise comes from `rng`.
    pub fn encode(
        &self,
        images: &Tensor,
        k: usize,
        rng: &mut StdRng,
    ) -> candle_core::Result<SlotOutput> {
        let tokens = self.encoder.forward(images)?;
        let mut out = self.slot_attention.forward(&tokens, k, rng)?;
        if self.cfg.zero_background {
            out.bg = out.bg.zeros_like()?;
        }
        Ok(out)
    }

    /// Runs the hypernetworks once: fg [B, K, D], bg [B, D] → the B·(1 + K) light fields,
    /// scene-major, background first in each scene.
    pub fn prepare(&self, fg: &Tensor, bg: &Tensor) -> candle_core::Result<SlotWeights> {
        let lf = self.light_field_or_err()?;
        let (b, k, d) = fg.dims3()?;
        let bg_w = SlotWeights {
            layers: lf.background.forward(bg)?,
        };
        if k == 0 {
            return Ok(bg_w);
        }
        let fg_w = SlotWeights {
            layers: lf.hypernet_fg.forward(&fg.reshape((b * k, d))?)?,
        };
        SlotWeights::join_scenes(&bg_w, Some(&fg_w), b, k)
    }

    /// Evaluates prepared light fields on encoded rays and composites them.
    pub fn decode(&self, fields: &SlotWeights, rays: &RayBatch) -> candle_core::Result<Decoded> {
        let lf = self.light_field_or_err()?;
        let (b, s, r) = (rays.scenes, rays.fields, rays.rays);
        if fields.num_fields()? != b * s {
            candle_core::bail!(
                "{} prepared light fields for {} scenes × {} fields of rays",
                fields.num_fields()?,
                b,
                s
            );
        }
        let features = fields.forward(&rays.coords)?; // [B·S, R, F]
        let (color, ordering) = lf.heads.forward(&features)?;
        let mut colors = color.reshape((b, s, r, 3))?.permute((0, 2, 1, 3))?; // [B, R, S, 3]
        let ordering = ordering.reshape((b, s, r))?.transpose(1, 2)?; // [B, R, S]
                                                                      // σ from the light field on each ray's shadow line (`shadow_light`), else on the ray.
        let shadow = match &rays.shadow_lines {
            Some((lines, on_ground)) => lf
                .heads
                .shadow(&fields.forward(lines)?)?
                .map(|sigma| {
                    sigma
                        .reshape((b, s, r))?
                        .broadcast_mul(&on_ground.reshape((b, 1, r))?)
                })
                .transpose()?,
            None => lf.heads.shadow(&features)?,
        };
        let shadow = match shadow {
            Some(sigma) => {
                // Only foreground slots cast shadows: the background's σ is reported as 0.
                let sigma = sigma.reshape((b, s, r))?.transpose(1, 2)?; // [B, R, S]
                let zero = sigma.narrow(2, 0, 1)?.zeros_like()?;
                if s == 1 {
                    Some(zero)
                } else {
                    let cast = sigma.narrow(2, 1, s - 1)?;
                    let lit = cast.sum_keepdim(2)?.neg()?.exp()?;
                    let shaded = colors.narrow(2, 0, 1)?.broadcast_mul(&lit.unsqueeze(3)?)?;
                    colors = Tensor::cat(&[&shaded, &colors.narrow(2, 1, s - 1)?], 2)?;
                    Some(Tensor::cat(&[&zero, &cast], 2)?)
                }
            }
            None => None,
        };
        let comp = lf
            .compositor
            .forward(&ordering.contiguous()?, &rays.shift)?;
        let rgb = comp.weights.unsqueeze(3)?.broadcast_mul(&colors)?.sum(2)?;
        Ok(Decoded {
            rgb,
            weights: comp.weights,
            log_weights: comp.log_weights,
            colors,
            ordering: comp.ordering,
            shadow,
        })
    }
}

/// Slot latents of one encoded image.
#[derive(Clone, Debug, PartialEq)]
pub struct Encoded {
    /// K foreground latents of size D.
    pub fg_latents: Vec<Vec<f32>>,
    /// The background latent (D).
    pub bg_latent: Vec<f32>,
    /// Each foreground slot's share of the image's attention, in [0, 1].
    pub slot_mass: Vec<f32>,
    /// Where each foreground slot attends: (x, y) in [0, 1] of the image (see `frames.rs`).
    pub fg_centroid: Vec<[f32; 2]>,
}

/// Light fields ready to render: the hypernetworks' outputs for one background and K foreground
/// slots, reusable for any number of rays, views and chunks.
#[derive(Clone, Debug)]
pub struct PreparedSlots {
    /// The generated light fields (None for a volumetric model).
    fields: Option<SlotWeights>,
    /// The latents, background first (what a volumetric model conditions on).
    latents: Vec<Vec<f32>>,
    num_fg: usize,
}

impl PreparedSlots {
    /// Number of foreground slots K.
    pub fn num_fg(&self) -> usize {
        self.num_fg
    }

    /// The generated light-field weights of the 1 + K fields (None for a volumetric model).
    pub fn light_fields(&self) -> Option<&SlotWeights> {
        self.fields.as_ref()
    }

    /// The 1 + K slot latents, background first.
    pub fn latents(&self) -> &[Vec<f32>] {
        &self.latents
    }
}

/// Per-ray render results, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct RayOutput {
    /// Composited colour, R×3, in [0, 1].
    pub rgb: Vec<f32>,
    /// Compositor weights R×(1 + K); column 0 is the background, column k + 1 slot k.
    pub weights: Vec<f32>,
    /// World-comparable ordering values R×(1 + K) (≈ distance along the ray from its origin,
    /// up to the model's learned offset), same columns.
    pub ordering: Vec<f32>,
    /// Shadow density σ R×(1 + K) that each slot casts on the background (`Config::shadow_head`;
    /// 0 for the background and for models without shadows), same columns.
    pub shadow: Vec<f32>,
    /// 1 + K.
    pub fields: usize,
}

impl RayOutput {
    /// Empty buffers with room for `rays` rays of `fields` fields, filled by appending.
    fn with_capacity(rays: usize, fields: usize) -> RayOutput {
        RayOutput {
            rgb: Vec::with_capacity(3 * rays),
            weights: Vec::with_capacity(fields * rays),
            ordering: Vec::with_capacity(fields * rays),
            shadow: Vec::with_capacity(fields * rays),
            fields,
        }
    }
}

/// A loaded model.
pub struct Colf {
    model: ColfModel,
    /// Every parameter by name (for a trainable model, the tensors of its `Var`s).
    params: BTreeMap<String, Tensor>,
    vars: Option<VarMap>,
    identity: String,
    device: Device,
}

/// Activation budget of one render chunk: S·rays·width floats ≤ this (8 MiB per tensor;
/// smaller chunks keep the element-wise passes in cache and measured faster than 64 MiB).
const CHUNK_FLOATS: usize = 1 << 21;

impl Colf {
    /// A freshly initialised model; every tensor drawn from a `StdRng` seeded by (seed, name).
    pub fn init(cfg: &Config, seed: u64) -> Result<Colf> {
        cfg.validate()?;
        let device = Device::Cpu;
        let backend = std::sync::Arc::new(init::SeededInit::new(seed));
        let vb = VarBuilder::from_backend(
            Box::new(SharedBackend(backend.clone())),
            DType::F32,
            device.clone(),
        );
        let model = ColfModel::new(cfg, vb).context("building the model")?;
        let params = backend.tensors();
        let identity = checkpoint::identity(&cfg.to_json(), &checkpoint::to_host(&params)?);
        Ok(Colf {
            model,
            params,
            vars: None,
            identity,
            device,
        })
    }

    /// Reads a model file (`name` is used in errors).
    pub fn from_bytes(bytes: &[u8], name: &str) -> Result<Colf> {
        let ckpt = checkpoint::from_bytes(bytes, name)?;
        let tensors = ckpt.tensors.into_iter().collect();
        Colf::build(ckpt.config, tensors, Some(ckpt.identity), name)
    }

    /// The same model under another config: one that gives every tensor the same name and
    /// shape (e.g. another `default_slots`), or that `grow.rs` can reach while computing the
    /// same function (`static_background`, a wider `hypernet_hidden`; new weights drawn from
    /// `seed`); anything else is refused, naming `name`.
    pub fn reconfigured(&self, cfg: &Config, seed: u64, name: &str) -> Result<Colf> {
        cfg.validate()?;
        let tensors = grow::grow_tensors(&self.model, &self.params, cfg, seed, name)?;
        Colf::build(cfg.clone(), tensors, None, name)
    }

    /// The same weights under a config changed by `overrides` (`KEY=VALUE`, as
    /// [`Config::with_overrides`]); refused unless every tensor keeps its name and shape.
    pub fn configured(&self, overrides: &[String]) -> Result<Colf> {
        let cfg = self.config().with_overrides(overrides)?;
        // `build` checks the tensors against the model the config describes: any missing,
        // unexpected or reshaped tensor is refused.
        Colf::build(cfg, self.params.clone(), None, "the new config").context(
            "the settings change the model's tensors (grow and train with --init and --set instead)",
        )
    }

    /// The same model with parameter `name` replaced by `value` (same shape), e.g. to set a
    /// shadow head's bias in a test; the identity is recomputed.
    pub fn with_tensor(&self, name: &str, value: Tensor) -> Result<Colf> {
        let Some(old) = self.params.get(name) else {
            bail!("the model has no tensor `{name}`");
        };
        if old.dims() != value.dims() {
            bail!(
                "tensor `{name}` has shape {:?}, not {:?}",
                old.dims(),
                value.dims()
            );
        }
        let mut tensors = self.params.clone();
        tensors.insert(name.to_string(), value.to_dtype(DType::F32)?);
        Colf::build(self.model.cfg.clone(), tensors, None, "model")
    }

    /// Builds the module tree of `cfg` on `tensors`, checking that the tensors are exactly the
    /// ones it asks for. `identity`: the file's, already checked; else computed.
    fn build(
        cfg: Config,
        tensors: BTreeMap<String, Tensor>,
        identity: Option<String>,
        name: &str,
    ) -> Result<Colf> {
        let device = Device::Cpu;
        let checked = std::sync::Arc::new(init::CheckedTensors::new(
            tensors.clone().into_iter().collect(),
        ));
        let vb = VarBuilder::from_backend(
            Box::new(SharedBackend(checked.clone())),
            DType::F32,
            device.clone(),
        );
        let built = ColfModel::new(&cfg, vb);
        let problems = checked.problems();
        if let Some(first) = problems.first() {
            let more = if problems.len() > 1 {
                format!(" (and {} more problems)", problems.len() - 1)
            } else {
                String::new()
            };
            bail!("{name}: {first}{more}; the file does not match its config");
        }
        let model = built.map_err(|e| anyhow!("{name}: {e}"))?;
        let identity = match identity {
            Some(id) => id,
            None => checkpoint::identity(&cfg.to_json(), &checkpoint::to_host(&tensors)?),
        };
        Ok(Colf {
            model,
            params: tensors,
            vars: None,
            identity,
            device,
        })
    }

    /// Reads a model file.
    pub fn load(path: &Path) -> Result<Colf> {
        let name = path.display().to_string();
        let bytes =
            std::fs::read(path).with_context(|| format!("{name}: cannot read the model"))?;
        Colf::from_bytes(&bytes, &name)
    }

    /// The model `explicit` names, else `$COLF_MODEL`, else the bundled default
    /// (see [`default_model_path`]).
    pub fn load_resolved(explicit: Option<&str>) -> Result<Colf> {
        Colf::load(&resolve_model_path(explicit)?)
    }

    /// The file bytes (deterministic) and the identity they carry.
    pub fn to_bytes(&self) -> Result<(Vec<u8>, String)> {
        let host = checkpoint::to_host(&self.params)?;
        Ok(checkpoint::to_bytes(&self.model.cfg, &host))
    }

    /// Writes the model file atomically (temporary file + rename in the target folder).
    pub fn save(&self, path: &Path) -> Result<String> {
        let (bytes, id) = self.to_bytes()?;
        crate::io::write_atomic(path, &bytes)?;
        Ok(id)
    }

    pub fn config(&self) -> &Config {
        &self.model.cfg
    }

    /// The module tree (differentiable calls for training).
    pub fn model(&self) -> &ColfModel {
        &self.model
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The identity of the weights as loaded or initialised; for a trainable model, of the
    /// current weights (recomputed).
    pub fn identity(&self) -> Result<String> {
        if self.vars.is_some() {
            return Ok(checkpoint::identity(
                &self.model.cfg.to_json(),
                &checkpoint::to_host(&self.params)?,
            ));
        }
        Ok(self.identity.clone())
    }

    /// Total number of parameters.
    pub fn num_parameters(&self) -> usize {
        self.params.values().map(|t| t.elem_count()).sum()
    }

    /// Parameter tensors by name.
    pub fn parameters(&self) -> &BTreeMap<String, Tensor> {
        &self.params
    }

    /// Turns the parameters into `Var`s and rebuilds the model on them, so gradients flow to
    /// them (see [`Colf::named_vars`]).
    pub fn into_trainable(self) -> Result<Colf> {
        if self.vars.is_some() {
            return Ok(self);
        }
        let varmap = VarMap::new();
        {
            let mut data = varmap.data().lock().map_err(|_| anyhow!("var map lock"))?;
            for (name, t) in &self.params {
                data.insert(name.clone(), Var::from_tensor(t)?);
            }
        }
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &self.device);
        let model = ColfModel::new(&self.model.cfg, vb)?;
        let params = varmap
            .data()
            .lock()
            .map_err(|_| anyhow!("var map lock"))?
            .iter()
            .map(|(n, v)| (n.clone(), v.as_tensor().clone()))
            .collect();
        Ok(Colf {
            model,
            params,
            vars: Some(varmap),
            identity: self.identity,
            device: self.device,
        })
    }

    /// The trainable `Var`s sorted by name (empty unless [`Colf::into_trainable`] was called).
    pub fn named_vars(&self) -> Vec<(String, Var)> {
        let Some(vars) = &self.vars else {
            return Vec::new();
        };
        let data = vars.data().lock().expect("var map lock");
        let mut all: Vec<(String, Var)> =
            data.iter().map(|(n, v)| (n.clone(), v.clone())).collect();
        all.sort_by(|a, b| a.0.cmp(&b.0));
        all
    }

    /// Encodes one RGB image (h×w×3, row-major, values in [0, 1]) into `num_slots` foreground
    /// slots and the background; the slot noise is drawn from `StdRng::seed_from_u64(seed)`.
    pub fn encode(
        &self,
        image_rgb: &[f32],
        h: usize,
        w: usize,
        num_slots: usize,
        seed: u64,
    ) -> Result<Encoded> {
        if h == 0 || w == 0 || image_rgb.len() != h * w * 3 {
            bail!(
                "image buffer of {} values does not hold a {w}×{h} RGB image",
                image_rgb.len()
            );
        }
        let image = encoder::image_tensor(&self.model.cfg, image_rgb, h, w, &self.device)?;
        let mut rng = StdRng::seed_from_u64(seed);
        let out = self.model.encode(&image, num_slots, &mut rng)?;
        let fg = out.fg.squeeze(0)?;
        let fg_latents = if num_slots == 0 {
            Vec::new()
        } else {
            fg.to_vec2::<f32>()?
        };
        let enc = Encoded {
            fg_latents,
            bg_latent: out.bg.squeeze(0)?.to_vec1::<f32>()?,
            slot_mass: out.fg_mass.squeeze(0)?.to_vec1::<f32>()?,
            fg_centroid: out
                .fg_centroid
                .squeeze(0)?
                .to_vec2::<f32>()?
                .into_iter()
                .map(|p| [p[0], p[1]])
                .collect(),
        };
        let finite = enc
            .bg_latent
            .iter()
            .chain(enc.fg_latents.iter().flatten())
            .all(|v| v.is_finite());
        if !finite {
            bail!("the encoder produced non-finite slot latents");
        }
        Ok(enc)
    }

    /// Runs the hypernetworks once for these slots.
    pub fn prepare(&self, fg_latents: &[Vec<f32>], bg_latent: &[f32]) -> Result<PreparedSlots> {
        let d = self.model.cfg.slot_dim;
        if bg_latent.len() != d || fg_latents.iter().any(|z| z.len() != d) {
            bail!("slot latents must have {d} values (the model's slot dimension)");
        }
        if bg_latent
            .iter()
            .chain(fg_latents.iter().flatten())
            .any(|v| !v.is_finite())
        {
            bail!("slot latents must be finite");
        }
        let k = fg_latents.len();
        let mut latents = vec![bg_latent.to_vec()];
        latents.extend(fg_latents.iter().cloned());
        if self.model.volumetric().is_some() {
            return Ok(PreparedSlots {
                fields: None,
                latents,
                num_fg: k,
            });
        }
        let flat: Vec<f32> = fg_latents.iter().flatten().copied().collect();
        let fg = Tensor::from_vec(flat, (1, k, d), &self.device)?;
        let bg = Tensor::from_vec(bg_latent.to_vec(), (1, d), &self.device)?;
        Ok(PreparedSlots {
            fields: Some(self.model.prepare(&fg, &bg)?),
            latents,
            num_fg: k,
        })
    }

    /// Rays per chunk that keep one activation tensor under `CHUNK_FLOATS`.
    pub fn rays_per_chunk(&self, fields: usize) -> usize {
        let cfg = &self.model.cfg;
        if let Some(v) = &cfg.volumetric {
            let width = v.hidden + v.pos_dim() + cfg.slot_dim;
            return (CHUNK_FLOATS / (fields * width * v.samples)).max(1);
        }
        let width = cfg
            .lfn_hidden
            .max(cfg.head_hidden)
            .max(cfg.compositor_hidden)
            .max(cfg.ray_input_dim());
        (CHUNK_FLOATS / (fields * width)).clamp(512, 16384)
    }

    /// Renders world rays (origins, directions; directions need not be unit) through prepared
    /// slots; slot k lives in frame `slot_to_world[k]`, the background in world space. Works in
    /// chunks so memory stays bounded whatever the number of rays or slots.
    pub fn render_rays(
        &self,
        prepared: &PreparedSlots,
        slot_to_world: &[DMat4],
        origins: &[DVec3],
        dirs: &[DVec3],
    ) -> Result<RayOutput> {
        let s = 1 + prepared.num_fg;
        if slot_to_world.len() != prepared.num_fg {
            bail!(
                "{} slot frames for {} slots",
                slot_to_world.len(),
                prepared.num_fg
            );
        }
        if origins.len() != dirs.len() {
            bail!(
                "{} ray origins but {} directions",
                origins.len(),
                dirs.len()
            );
        }
        let r = origins.len();
        if let Some(vol) = self.model.volumetric() {
            return self.render_rays_volumetric(vol, prepared, slot_to_world, origins, dirs);
        }
        let fields = prepared
            .fields
            .as_ref()
            .ok_or_else(|| anyhow!("slots were prepared for another kind of model"))?;
        let mut out = RayOutput::with_capacity(r, s);
        let chunk = self.rays_per_chunk(s);
        for start in (0..r).step_by(chunk) {
            let end = (start + chunk).min(r);
            let rays = RayBatch::new(
                &self.model.cfg,
                &[SceneRays {
                    slot_to_world,
                    origins: &origins[start..end],
                    dirs: &dirs[start..end],
                }],
                &self.device,
            )?;
            let dec = self.model.decode(fields, &rays)?;
            out.rgb.extend(dec.rgb.flatten_all()?.to_vec1::<f32>()?);
            out.weights
                .extend(dec.weights.flatten_all()?.to_vec1::<f32>()?);
            let ordering = dec.ordering.flatten_all()?.to_vec1::<f32>()?;
            for (i, o) in ordering.iter().enumerate() {
                out.ordering.push((*o as f64 + rays.base[i / s]) as f32);
            }
            match &dec.shadow {
                Some(sigma) => out.shadow.extend(sigma.flatten_all()?.to_vec1::<f32>()?),
                None => out.shadow.resize(out.ordering.len(), 0.0),
            }
        }
        Ok(out)
    }
}

impl Colf {
    /// The volumetric reference render (candle ops, `samples` from the config), in chunks.
    fn render_rays_volumetric(
        &self,
        vol: &volumetric::Volumetric,
        prepared: &PreparedSlots,
        slot_to_world: &[DMat4],
        origins: &[DVec3],
        dirs: &[DVec3],
    ) -> Result<RayOutput> {
        let s = 1 + prepared.num_fg;
        let d = self.model.cfg.slot_dim;
        for (k, m) in slot_to_world.iter().enumerate() {
            let det = m.determinant();
            if !m.is_finite() || !det.is_finite() || det.abs() < 1e-12 {
                bail!("slot {k}'s slot_to_world is not an invertible finite matrix");
            }
        }
        for (i, (o, dir)) in origins.iter().zip(dirs).enumerate() {
            if !o.is_finite() || !dir.is_finite() || dir.length_squared() < 1e-24 {
                bail!("ray {i} has a non-finite origin or a zero/non-finite direction");
            }
        }
        let flat: Vec<f32> = prepared.latents.iter().flatten().copied().collect();
        let latents = Tensor::from_vec(flat, (s, d), &self.device)?;
        let r = origins.len();
        let mut out = RayOutput::with_capacity(r, s);
        let chunk = self.rays_per_chunk(s);
        for start in (0..r).step_by(chunk) {
            let end = (start + chunk).min(r);
            let v = vol.render_reference(
                &latents,
                slot_to_world,
                &origins[start..end],
                &dirs[start..end],
                vol.cfg.samples,
            )?;
            out.rgb.extend(v.rgb.flatten_all()?.to_vec1::<f32>()?);
            out.weights
                .extend(v.weights.flatten_all()?.to_vec1::<f32>()?);
            out.ordering
                .extend(v.depth.flatten_all()?.to_vec1::<f32>()?);
        }
        out.shadow.resize(out.ordering.len(), 0.0);
        Ok(out)
    }
}

/// Lets a backend be kept by the caller after the `VarBuilder` took it.
struct SharedBackend<B>(std::sync::Arc<B>);

impl<B: candle_nn::var_builder::SimpleBackend> candle_nn::var_builder::SimpleBackend
    for SharedBackend<B>
{
    fn get(
        &self,
        s: candle_core::Shape,
        name: &str,
        h: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        self.0.get(s, name, h, dtype, dev)
    }
    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        self.0.get_unchecked(name, dtype, dev)
    }
    fn contains_tensor(&self, name: &str) -> bool {
        self.0.contains_tensor(name)
    }
}

/// File name of the bundled default model.
pub const DEFAULT_MODEL_FILE: &str = "default.safetensors";

/// Where the bundled default model is looked for, in order:
/// 1. `<folder of the running program>/../share/colf/default.safetensors` — where
///    `make install` puts it beside `$(PREFIX)/bin`;
/// 2. `<source tree>/models/default.safetensors` (the path of the crate when it was built) —
///    a fresh clone's `target/release/colf-*` and `cargo run` find it there.
pub fn default_model_candidates() -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Some(dir) = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent().map(Path::to_path_buf))
    {
        out.push(dir.join("../share/colf").join(DEFAULT_MODEL_FILE));
    }
    out.push(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("models")
            .join(DEFAULT_MODEL_FILE),
    );
    out
}

/// The default model: `$COLF_MODEL` when set (and not empty), else the first existing
/// [`default_model_candidates`] entry.
pub fn default_model_path() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("COLF_MODEL").filter(|p| !p.is_empty()) {
        return Ok(PathBuf::from(p));
    }
    let candidates = default_model_candidates();
    candidates
        .iter()
        .find(|p| p.is_file())
        .cloned()
        .ok_or_else(|| {
            let list: Vec<String> = candidates.iter().map(|p| p.display().to_string()).collect();
            anyhow!(
                "no model given and no default model found (set COLF_MODEL or pass --model; looked in {})",
                list.join(", ")
            )
        })
}

/// `explicit` (a `--model` argument) if given, else [`default_model_path`].
pub fn resolve_model_path(explicit: Option<&str>) -> Result<PathBuf> {
    match explicit {
        Some(p) => Ok(PathBuf::from(p)),
        None => default_model_path(),
    }
}

/// `colf-train init`: writes a freshly initialised model of `preset` to `output` (`-`: stdout)
/// and returns a one-line summary (preset, parameters, size, identity).
pub fn init_model_file(
    preset: &str,
    overrides: &[String],
    seed: u64,
    output: &str,
) -> Result<String> {
    let cfg = Config::preset(preset)?.with_overrides(overrides)?;
    let model = Colf::init(&cfg, seed)?;
    let (bytes, id) = model.to_bytes()?;
    crate::io::write_output(output, &bytes, true)?;
    Ok(format!(
        "wrote {} (preset {preset}, seed {seed}, {} parameters, {} bytes, identity {id})",
        if crate::io::is_stdio(output) {
            "<stdout>"
        } else {
            output
        },
        model.num_parameters(),
        bytes.len()
    ))
}
