//! [`Colf`]: a loaded model — the [`ColfNet`] with its parameters, identity and device — and
//! the host-side API the stages use: encode an image into slot latents, prepare slots (the
//! hypernetworks run once per slot), render any number of world rays in bounded-memory chunks,
//! and save or load the model file.

use super::history::TrainingRun;
use super::*;
use anyhow::{anyhow, bail, Context, Result};
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use glam::{DMat4, DVec3};
use rand::rngs::StdRng;
use rand::SeedableRng;
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

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
    /// How far down the image each foreground slot's attention reaches, y in [0, 1].
    pub fg_bottom: Vec<f32>,
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
    /// Zeroed buffers for `rays` rays of `fields` fields, filled in place.
    pub fn zeros(rays: usize, fields: usize) -> RayOutput {
        RayOutput {
            rgb: vec![0.0; 3 * rays],
            weights: vec![0.0; fields * rays],
            ordering: vec![0.0; fields * rays],
            shadow: vec![0.0; fields * rays],
            fields,
        }
    }

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
    model: ColfNet,
    /// Every parameter by name (for a trainable model, the tensors of its `Var`s).
    params: BTreeMap<String, Tensor>,
    vars: Option<VarMap>,
    identity: String,
    device: Device,
    /// How the model was trained (the file's `training` records; empty if unknown).
    training: Vec<TrainingRun>,
    /// Parameters written in half precision (those read so, or chosen by
    /// [`Colf::with_half_storage`]); the rest are written as f32.
    half: BTreeSet<String>,
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
        let model = ColfNet::new(cfg, vb).context("building the model")?;
        let params = backend.tensors();
        let identity = checkpoint::identity(&cfg.to_json(), &checkpoint::to_host(&params)?);
        Ok(Colf {
            model,
            params,
            vars: None,
            identity,
            device,
            training: Vec::new(),
            half: BTreeSet::new(),
        })
    }

    /// Reads a model file (`name` is used in errors).
    pub fn from_bytes(bytes: &[u8], name: &str) -> Result<Colf> {
        let ckpt = checkpoint::from_bytes(bytes, name)?;
        let tensors = ckpt.tensors.into_iter().collect();
        let mut model = Colf::build(ckpt.config, tensors, Some(ckpt.identity), name)?
            .with_training(ckpt.training);
        model.half = ckpt.half;
        Ok(model)
    }

    /// The same model under another config: one that gives every tensor the same name and
    /// shape (e.g. another `default_slots`), or that `grow.rs` can reach while computing the
    /// same function (`static_background`, a wider `hypernet_hidden`; new weights drawn from
    /// `seed`); anything else is refused, naming `name`.
    pub fn reconfigured(&self, cfg: &Config, seed: u64, name: &str) -> Result<Colf> {
        self.grown(cfg, grow::Growth::seeded(seed), name)
    }

    /// As [`Colf::reconfigured`], with the growth's choices (e.g. a wider `slot_dim`'s fresh
    /// values) given.
    pub fn grown(&self, cfg: &Config, growth: grow::Growth, name: &str) -> Result<Colf> {
        cfg.validate()?;
        let tensors = grow::grow_tensors(&self.model, &self.params, cfg, growth, name)?;
        Ok(Colf::build(cfg.clone(), tensors, None, name)?.with_training(self.training.clone()))
    }

    /// The same weights under a config changed by `overrides` (`KEY=VALUE`, as
    /// [`Config::with_overrides`]); refused unless every tensor keeps its name and shape.
    pub fn configured(&self, overrides: &[String]) -> Result<Colf> {
        let cfg = self.config().with_overrides(overrides)?;
        // `build` checks the tensors against the model the config describes: any missing,
        // unexpected or reshaped tensor is refused.
        let configured = Colf::build(cfg, self.params.clone(), None, "the new config").context(
            "the settings change the model's tensors (grow the model and train it from this one instead)",
        )?;
        let mut configured = configured.with_training(self.training.clone());
        configured.half = self.half.clone();
        Ok(configured)
    }

    /// The same model, to be written with every parameter of at least `min_values` values in
    /// half precision (IEEE f16; the hypernetworks' heads, nearly all of a model's bytes). The
    /// written file holds the rounded weights and its identity is theirs; a value beyond f16's
    /// range is refused, naming the tensor.
    pub fn with_half_storage(mut self, min_values: usize) -> Result<Colf> {
        self.half = self
            .params
            .iter()
            .filter(|(_, t)| t.elem_count() >= min_values)
            .map(|(n, _)| n.clone())
            .collect();
        for name in &self.half {
            let t = &self.params[name];
            let largest = t.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            if largest > f32::from(half::f16::MAX) {
                bail!("tensor `{name}` has a value of magnitude {largest}, beyond half precision's range");
            }
        }
        Ok(self)
    }

    /// The parameters written in half precision.
    pub fn half_tensors(&self) -> &BTreeSet<String> {
        &self.half
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
        Ok(Colf::build(self.model.cfg.clone(), tensors, None, "model")?
            .with_training(self.training.clone()))
    }

    /// How the model was trained, oldest run first (empty when its file did not say).
    pub fn training(&self) -> &[TrainingRun] {
        &self.training
    }

    /// The same model with these training records.
    pub fn with_training(mut self, training: Vec<TrainingRun>) -> Colf {
        self.training = training;
        self
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
        let built = ColfNet::new(&cfg, vb);
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
            training: Vec::new(),
            half: BTreeSet::new(),
        })
    }

    /// Reads a model file.
    pub fn load(path: &Path) -> Result<Colf> {
        let name = path.display().to_string();
        let bytes =
            std::fs::read(path).with_context(|| format!("{name}: cannot read the model"))?;
        Colf::from_bytes(&bytes, &name)
    }

    /// The file bytes (deterministic) and the identity they carry.
    pub fn to_bytes(&self) -> Result<(Vec<u8>, String)> {
        let host = checkpoint::to_host(&self.params)?;
        Ok(checkpoint::to_bytes(
            &self.model.cfg,
            &host,
            &self.training,
            &self.half,
        ))
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
    pub fn model(&self) -> &ColfNet {
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
        let model = ColfNet::new(&self.model.cfg, vb)?;
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
            training: self.training,
            half: BTreeSet::new(),
        })
    }

    /// Decode through candle's autograd instead of the fused kernel (see
    /// `ColfNet::reference_decoder`).
    pub fn set_reference_decoder(&mut self, on: bool) {
        self.model.reference_decoder = on;
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
        self.encode_within(image_rgb, h, w, num_slots, seed, None)
    }

    /// As [`Colf::encode`]; with `objects` (h×w, 1 on object pixels and 0 elsewhere) the
    /// foreground slots are placed from the part of their attention on those pixels
    /// (`Config::frames_from_residual`, `SlotOutput::attend_within`).
    pub fn encode_within(
        &self,
        image_rgb: &[f32],
        h: usize,
        w: usize,
        num_slots: usize,
        seed: u64,
        objects: Option<&[f32]>,
    ) -> Result<Encoded> {
        if h == 0 || w == 0 || image_rgb.len() != h * w * 3 {
            bail!(
                "image buffer of {} values does not hold a {w}×{h} RGB image",
                image_rgb.len()
            );
        }
        let image = encoder::image_tensor(&self.model.cfg, image_rgb, h, w, &self.device)?;
        let mut rng = StdRng::seed_from_u64(seed);
        let mut out = self.model.encode(&image, num_slots, &mut rng)?;
        if let Some(objects) = objects {
            out.attend_within_pixels(&[(objects, h, w)], super::frames::MIN_OBJECT_SHARE)?;
        }
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
            fg_bottom: out.fg_bottom.squeeze(0)?.to_vec1::<f32>()?,
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
            // The volumetric reference render (candle ops, `samples` from the config).
            rays::world_to_slot(slot_to_world)?;
            rays::check_rays(origins, dirs)?;
            let d = self.model.cfg.slot_dim;
            let flat: Vec<f32> = prepared.latents.iter().flatten().copied().collect();
            let latents = Tensor::from_vec(flat, (s, d), &self.device)?;
            return self.in_chunks(origins.len(), s, |range, out| {
                let v = vol.render_reference(
                    &latents,
                    slot_to_world,
                    &origins[range.clone()],
                    &dirs[range],
                    vol.cfg.samples,
                )?;
                out.rgb.extend(v.rgb.flatten_all()?.to_vec1::<f32>()?);
                out.weights
                    .extend(v.weights.flatten_all()?.to_vec1::<f32>()?);
                out.ordering
                    .extend(v.depth.flatten_all()?.to_vec1::<f32>()?);
                out.shadow.resize(out.ordering.len(), 0.0);
                Ok(())
            });
        }
        let fields = prepared
            .fields
            .as_ref()
            .ok_or_else(|| anyhow!("slots were prepared for another kind of model"))?;
        self.in_chunks(r, s, |range, out| {
            let rays = RayBatch::new(
                &self.model.cfg,
                &[SceneRays {
                    slot_to_world,
                    origins: &origins[range.clone()],
                    dirs: &dirs[range],
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
            Ok(())
        })
    }

    /// Renders `r` rays with `s` fields in chunks of bounded memory: `render(rays, out)` appends
    /// the outputs of the rays `rays` to `out`.
    fn in_chunks(
        &self,
        r: usize,
        s: usize,
        mut render: impl FnMut(std::ops::Range<usize>, &mut RayOutput) -> Result<()>,
    ) -> Result<RayOutput> {
        let mut out = RayOutput::with_capacity(r, s);
        let chunk = self.rays_per_chunk(s);
        for start in (0..r).step_by(chunk) {
            render(start..(start + chunk).min(r), &mut out)?;
        }
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
