//! Model sizes and knobs. A `Config` is stored (as JSON) inside every checkpoint, so a model file
//! is self-describing; `small` trains on a 2-core CPU, `paper` follows the COLF supplement §1.

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

pub(crate) fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

pub(crate) fn is_zero_count(v: &usize) -> bool {
    *v == 0
}

/// The most octaves `floor_fourier_freqs` may ask for: the finest period is then 2^(1−L) =
/// 2⁻¹¹ world units, far below a pixel of any scene colf renders.
pub const MAX_FLOOR_FOURIER_FREQS: usize = 12;

/// Every size and knob of a COLF model. Unknown keys are refused when a checkpoint is read, so
/// a file written by a newer colf with new knobs is reported instead of silently misread.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Name of the preset this config started from (informational).
    pub preset: String,
    /// Side of the square image the encoder sees; inputs are resized to it.
    pub encoder_size: usize,
    /// Stride of the encoder's first conv layer: 1 follows the supplement (tokens at full
    /// encoder resolution), 2 halves the token grid (the `small` preset: 64² input → 32² tokens).
    pub encoder_first_stride: usize,
    /// Channels of the first (full-resolution) conv layer.
    pub encoder_channels: usize,
    /// Channels of the downsampled conv layers.
    pub encoder_channels_low: usize,
    /// Channels of the feature grid the slots attend to.
    pub feature_dim: usize,
    /// Slot latent size D.
    pub slot_dim: usize,
    /// Slot-attention iterations.
    pub slot_iters: usize,
    /// Hidden width of the slots' residual MLPs.
    pub slot_mlp_hidden: usize,
    /// Foreground slots K used when the caller does not choose.
    pub default_slots: usize,
    /// Hidden width of every light-field MLP.
    pub lfn_hidden: usize,
    /// Number of hidden layers of every light-field MLP.
    pub lfn_hidden_layers: usize,
    /// Size of the ray feature a light field outputs.
    pub lfn_features: usize,
    /// Fourier frequencies per ray coordinate (0: the raw 6-D Plücker ray is the input).
    pub ray_fourier_freqs: usize,
    /// Floor features of the background light field (0 = none): octaves L of sin/cos of the
    /// point where a camera ray meets the floor plane z = 0 (world +Z up). The background
    /// cannot draw a high-frequency floor texture (parquet, tiles) from the ray's Plücker
    /// coordinates alone; these give it the texture's coordinates directly. The background's
    /// input gains 3 + 4·L columns after the Plücker coordinates and their Fourier features: a
    /// hit flag, the hit point's (x, y)/`scene_scale` bounded as the moment is, and sin/cos of
    /// 2^k·π·x and 2^k·π·y for k < L, x and y in world units (periods 2, 1, ½, … world units;
    /// see `rays.rs`). All zero on a ray that does not meet the floor ahead of its origin, and
    /// in every foreground slot's input and every shadow line. Light-field models only; a model
    /// grows to it with unchanged renders (zero weights on the new inputs). Absent in older
    /// files (= 0), and not written when 0, so their identity is unchanged.
    #[serde(default, skip_serializing_if = "is_zero_count")]
    pub floor_fourier_freqs: usize,
    /// Hidden width of the hypernetworks (one hidden layer).
    pub hypernet_hidden: usize,
    /// Hidden width of the colour and ordering heads.
    pub head_hidden: usize,
    /// Hidden layers of the colour and ordering heads.
    pub head_hidden_layers: usize,
    /// Hidden width of the compositor MLP V.
    pub compositor_hidden: usize,
    /// Hidden layers of the compositor MLP V.
    pub compositor_hidden_layers: usize,
    /// World length that maps to 1 in the networks' inputs: Plücker moments are divided by it
    /// (then smoothly bounded), ordering values are produced in these units.
    pub scene_scale: f64,
    /// World length that divides a foreground slot's Plücker moments instead of `scene_scale`
    /// (0 = `scene_scale`, as before). An object lies within a unit or so of its slot's frame
    /// origin, so at the scene's scale its rays' moments span a small part of the bounded range
    /// and the Fourier octaves are coarse across it; a smaller length gives the same octaves
    /// finer detail on the object. The background keeps `scene_scale`. Absent in older files
    /// (= 0), and not written when 0, so their identity is unchanged.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub slot_scale: f64,
    /// The background is rendered from a zero latent, whatever the image (the paper's choice
    /// for CLEVR): the background cannot explain image-specific content, which is left to the
    /// foreground slots. Applied inside the model, so training and inference agree. Absent in
    /// older files (= false), and not written when false, so their identity is unchanged.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub zero_background: bool,
    /// With `zero_background`: the background light field's weights are parameters of their own
    /// (`background_field.`), not a hypernetwork's output. A hypernetwork fed a constant zero
    /// latent only ever produces one set of weights, so this is the same family of models with
    /// ~30 thousand background parameters instead of ~2 million (room for a larger foreground
    /// decoder within the same file size). Absent in older files (= false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub static_background: bool,
    /// The background latent is read from the whole image — the mean of the encoder's tokens,
    /// projected to the slot size (`background_reader.`) — instead of
    /// taken from slot attention's background slot, which still competes for the pixels.
    /// Slot attention trained with a zero background never learns to put what differs between
    /// images into that slot; the mean of the features always carries the floor's brightness
    /// and the light, so the background can follow a scene's look. Needs an image-dependent
    /// background (`zero_background` off). Absent in older files (= false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub background_reader: bool,
    /// Divide each slot latent by its root-mean-square before the hypernetworks, so the scale
    /// of the generated light-field weights does not follow the scale of the latent (slot
    /// latents reach norms of ~20 and vary between scenes; without this, training was spiky).
    /// Absent in older files (= false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub hypernet_rms_norm: bool,
    /// Give each light-field layer's heads a hidden layer of their own (`layers.{l}.fc1.`)
    /// instead of one shared by all (`fc1.`), as SIREN's and LFN's hypernetworks give each
    /// generated tensor its own MLP: a slot's light field then ranges over an affine subspace of
    /// L·H dimensions instead of H (L light-field layers), for the same head parameters and no
    /// more work per ray. Absent in older files (= false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub hypernet_per_layer: bool,
    /// Place each foreground slot's frame where the slot attends in the image (see
    /// `frames.rs`), instead of at the camera. Absent in older files (= false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub attention_frames: bool,
    /// Locality bound of foreground slots, world units (0 = none): on a ray passing at
    /// distance ρ from a slot's frame origin, the slot's ordering value is pushed back by ρ²/r
    /// (see `rays.rs`). Absent in older files (= 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub fg_locality: f64,
    /// The background's ordering value on a ray is measured from the nearest foreground frame
    /// origin along it (the smallest (t − o)·d̂ over the slots) instead of from the world
    /// origin. On scenes much longer than `scene_scale` (a street, a merged scene) the world
    /// origin can lie tens of units in front of the objects on a ray, and no bounded ordering
    /// output can put the background behind them; from the nearest slot it can, anywhere.
    /// Without slots it falls back to the world origin. Absent in older files (= false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub background_from_nearest_slot: bool,
    /// With `attention_frames`, scenes whose objects rest on the ground plane z = 0 (world +Z
    /// up, as in clevr567): each foreground frame's origin is where the slot's centroid ray
    /// meets the plane z = this height (about an object's centre height), instead of at the
    /// scene centre's depth — so a slot's object sits near its frame origin in 3D, not only in
    /// the image (see `frames.rs`). 0 = off. Absent in older files (= 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub frame_ground_height: f64,
    /// With `attention_frames`, scenes whose objects rest on the ground plane z = 0 seen from
    /// a low camera (a street): each foreground frame's depth along its centroid ray is that of
    /// the point where the ray through the lower edge of the slot's attention (the object's
    /// contact with the ground) meets z = 0, instead of the scene centre's depth. Unlike
    /// `frame_ground_height`, whose plane a low camera's rays to an object's centre graze, the
    /// contact ray points at the ground below the object (`frames.rs`). Absent in older files
    /// (= false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub frame_ground_contact: bool,
    /// With `attention_frames` and a static background (scenes that share one background, a
    /// street): each foreground slot is placed from the part of its attention on the pixels
    /// the background does not draw — object proposals against the background's render at the
    /// input camera (`proposals.rs`) — rather than from all of it, where that part is at least
    /// `frames::MIN_OBJECT_SHARE` of it. Slot attention spreads beyond a small object, so its
    /// centroid and lower edge read off the object; within the object's pixels they are the
    /// object's. In training the input view's object ids are the pixels: its proposals with
    /// `--proposals`, else its mask file (a run with neither is refused). Absent in older
    /// files (= false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub frames_from_residual: bool,
    /// A foreground slot does not draw on a ray that starts more than this (world units) past
    /// its frame origin (the origin lies that far behind the camera, along the ray), and the
    /// background's ordering is not measured from it: an object within this of its frame
    /// origin cannot be seen there. Without it, a slot behind a camera that stands among the
    /// objects (a drive down a street, a view from another row) gets the most negative
    /// ordering shift and is drawn in front of everything (`rays.rs`). 0 = off. Absent in
    /// older files (= 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub cull_behind: f64,
    /// Foreground slots cast shadows on the background: each slot's light field also gives a
    /// shadow density σ ≥ 0 per ray (`heads.shadow`), and the background's colour on a ray is
    /// multiplied by exp(−Σ σ) over the foreground slots. The shadow belongs to the object's
    /// slot, so it moves, duplicates and disappears with it in edits, and the pixel stays the
    /// background's in the segmentation. Absent in older files (= false).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub shadow_head: bool,
    /// With `shadow_head`, scenes on the ground plane z = 0 (world +Z up) lit by a distant light
    /// at [azimuth, elevation] degrees (clevr567: about [30, 55]): a slot's shadow density on a
    /// ray is read from its light field on the ray's *shadow line* — from where the ray meets
    /// the ground toward the light — instead of on the ray itself. The light field already
    /// knows which lines pass through its object (that is what its ordering and the mask losses
    /// train), so the point is in shadow exactly when that line hits the object. Costs a second
    /// light-field evaluation per ray and slot. Absent = shadows read from the ray itself.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shadow_light: Option<[f64; 2]>,
    /// With `shadow_light`: a foreground slot casts no shadow on a ray whose shadow line passes
    /// farther than this from the slot's frame origin (frame units; 0 = no bound). Otherwise a
    /// slot's light field must learn that lines far from its object carry no shadow, and every
    /// such line costs an evaluation: on clevr567, lines beyond 5 units are over half of them
    /// and their learnt σ averages 10⁻⁵ (`docs/speed.md`). Decided from the encoded line's
    /// bounded moment ([`Config::shadow_reach_bound`]), so the decode kernel, the candle
    /// reference and the renderers skip the same lines. Absent in older files (= 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub shadow_reach: f64,
    /// A foreground slot is absent on a camera ray whose line passes farther than this from
    /// the slot's frame origin (frame units; 0 = no bound): there it has no colour, compositor
    /// weight 0, ordering +∞ and casts no shadow, and its light field is not evaluated. Slots
    /// draw objects near their frames; without a bound every slot's light field runs on every
    /// ray, and on clevr567 three quarters of those evaluations are beyond 3 units, where the
    /// paper-sized decoder's slots hold compositor weights averaging 7·10⁻⁴ (`docs/speed.md`).
    /// Decided from the encoded ray's bounded moment ([`Config::slot_reach_bound`]), so the
    /// decode kernel, the candle reference and the renderers leave out the same evaluations.
    /// Light-field models only. Absent in older files (= 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub slot_reach: f64,
    /// Which decoder turns slots into pixels: absent (the default) = COLF's light fields (one
    /// network evaluation per ray per slot); present = the uORF-style volumetric baseline of
    /// `volumetric.rs` with these sizes (per-slot NeRF MLP conditioned on the latent, samples
    /// along each ray, density-weighted slot composition, alpha compositing). A volumetric model
    /// keeps the encoder and slot attention; the `lfn_*`, `hypernet_*`, `head_*` and
    /// `compositor_*` sizes are then unused. Not written when absent, so the files and
    /// identities of light-field models are unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volumetric: Option<VolumetricConfig>,
    /// How `colf-encode` and `colf-eval` encode an image with this model when their flags do
    /// not say (`--fast` and the flags still choose): settings measured for this model, written
    /// by `colf-train configure`. Absent = one encoder pass with `default_slots`. Not written
    /// when absent, so older files and their identities are unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inference: Option<InferenceConfig>,
}

/// The encoding a model is used with by default (see `encode.rs`): more slots than it was
/// trained with, the best of several slot-noise seeds, then test-time refinement of the latents
/// on the input image.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InferenceConfig {
    /// Foreground slots K.
    pub slots: usize,
    /// Encodings (slot-noise seeds) tried; the one that reconstructs the input best is kept.
    pub tries: usize,
    /// Refinement steps on the input image (0: the encoder's latents).
    pub refine: usize,
    /// Refinement's learning rate on the latents (absent: colf-encode's `--refine-lr` default).
    /// Not written when absent, so older files and their identities are unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refine_lr: Option<f64>,
    /// Refinement's learning rate on the slot frames' origins, world units (absent:
    /// `--refine-frame-lr`'s default; 0: frames fixed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refine_frame_lr: Option<f64>,
    /// Pixels of the input image each refinement step renders (absent: `RefineOptions`'
    /// default, 1,024): a larger decoder can keep the encoding's cost with fewer.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refine_rays: Option<usize>,
    /// Refinement's mask loss against the views' object proposals, for a model with a static
    /// background (`RefineOptions::mask_weight`; absent: `--refine-mask`'s default, 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refine_mask: Option<f64>,
    /// Unsure proposal pixels within this many pixels of an object counted to it in that mask
    /// loss (`RefineOptions::mask_claim`; absent: 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refine_mask_claim: Option<usize>,
}

/// Largest slot count an encoding accepts: slot attention runs with any K, but beyond this a
/// typo (`--slots 100000`) would only burn memory.
pub const MAX_ENCODE_SLOTS: usize = 1024;
/// Largest number of tries: each try is one encoder pass and one render of the input view.
pub const MAX_ENCODE_TRIES: usize = 100;
/// Largest `inference.refine` a config may ask for (a typo would cost every encode).
const MAX_INFERENCE_REFINE: usize = 100_000;
/// Largest refinement learning rate a config or colf-encode's flags may ask for: latents live in
/// a unit-scale space, so a step far above 1 can only overflow.
pub const MAX_REFINE_LR: f64 = 100.0;
/// Largest `inference.refine_mask_claim`, pixels (the trainer's claims are 1–3).
const MAX_INFERENCE_MASK_CLAIM: usize = 64;
/// Largest `inference.refine_rays`: a 1024² image's pixels (more is a typo, and memory).
const MAX_INFERENCE_REFINE_RAYS: usize = 1 << 20;

impl InferenceConfig {
    /// One encoder pass with `slots` slots.
    pub fn one_pass(slots: usize) -> InferenceConfig {
        InferenceConfig {
            slots,
            tries: 1,
            refine: 0,
            refine_lr: None,
            refine_frame_lr: None,
            refine_rays: None,
            refine_mask: None,
            refine_mask_claim: None,
        }
    }
}

/// Sizes of the volumetric (uORF-style) baseline decoder; see `volumetric.rs`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumetricConfig {
    /// Width of every hidden layer (uORF: 64).
    pub hidden: usize,
    /// ReLU layers before the skip connection, the first taking [γ(p), z] (uORF: 3).
    pub layers_before_skip: usize,
    /// ReLU layers from the skip connection on, the first taking [h, γ(p), z] (uORF: 3).
    pub layers_after_skip: usize,
    /// Hidden width of the colour head (uORF: 32).
    pub color_hidden: usize,
    /// Positional-encoding frequencies per coordinate: γ(p) = [p, sin(2^k·π·p), cos(2^k·π·p)],
    /// k < L (uORF: 5, so 33 inputs).
    pub pos_freqs: usize,
    /// Samples per ray when the caller does not choose (uORF: 64).
    pub samples: usize,
    /// Near and far bounds of the samples along the ray, world units from the ray origin
    /// (uORF on CLEVR: 6 and 20).
    pub near: f64,
    pub far: f64,
}

impl VolumetricConfig {
    /// uORF's decoder sizes.
    pub fn uorf() -> VolumetricConfig {
        VolumetricConfig {
            hidden: 64,
            layers_before_skip: 3,
            layers_after_skip: 3,
            color_hidden: 32,
            pos_freqs: 5,
            samples: 64,
            near: 6.0,
            far: 20.0,
        }
    }

    /// Size of the positional encoding γ(p).
    pub fn pos_dim(&self) -> usize {
        3 * (1 + 2 * self.pos_freqs)
    }

    fn validate(&self) -> Result<()> {
        if self.hidden == 0
            || self.layers_before_skip == 0
            || self.layers_after_skip == 0
            || self.color_hidden == 0
            || self.samples == 0
        {
            bail!("model config: volumetric sizes must be positive");
        }
        if self.pos_freqs > 16 || self.hidden > 4096 || self.samples > 4096 {
            bail!("model config: a volumetric size is implausibly large");
        }
        if !(self.near.is_finite()
            && self.far.is_finite()
            && 0.0 <= self.near
            && self.near < self.far)
        {
            bail!("model config: volumetric `near` and `far` must satisfy 0 ≤ near < far");
        }
        Ok(())
    }
}

impl Config {
    /// The CPU-trainable preset (≈ 3 M parameters).
    pub fn small() -> Config {
        Config {
            preset: "small".into(),
            encoder_size: 64,
            encoder_first_stride: 2,
            encoder_channels: 32,
            encoder_channels_low: 64,
            feature_dim: 64,
            slot_dim: 64,
            slot_iters: 3,
            slot_mlp_hidden: 128,
            default_slots: 7,
            lfn_hidden: 128,
            lfn_hidden_layers: 2,
            lfn_features: 32,
            ray_fourier_freqs: 0,
            floor_fourier_freqs: 0,
            hypernet_hidden: 64,
            head_hidden: 64,
            head_hidden_layers: 1,
            compositor_hidden: 32,
            compositor_hidden_layers: 1,
            scene_scale: 8.0,
            slot_scale: 0.0,
            zero_background: false,
            static_background: false,
            background_reader: false,
            hypernet_rms_norm: true,
            hypernet_per_layer: false,
            attention_frames: false,
            fg_locality: 0.0,
            background_from_nearest_slot: false,
            frame_ground_height: 0.0,
            frame_ground_contact: false,
            frames_from_residual: false,
            cull_behind: 0.0,
            shadow_head: false,
            shadow_light: None,
            shadow_reach: 0.0,
            slot_reach: 0.0,
            volumetric: None,
            inference: None,
        }
    }

    /// The sizes of the COLF supplement §1: encoder at 128², slot dim 128, light fields with
    /// 2 hidden layers of 256 → 64 features, heads and compositor with 3 hidden layers of 128,
    /// hypernetworks with 1 hidden layer (width 128, not stated in the paper).
    pub fn paper() -> Config {
        Config {
            preset: "paper".into(),
            encoder_size: 128,
            encoder_first_stride: 1,
            encoder_channels: 64,
            slot_dim: 128,
            lfn_hidden: 256,
            lfn_features: 64,
            hypernet_hidden: 128,
            head_hidden: 128,
            head_hidden_layers: 3,
            compositor_hidden: 128,
            compositor_hidden_layers: 3,
            ..Config::small()
        }
    }

    /// The volumetric baseline: the `small` encoder and slot attention (slot dim 64, uORF's
    /// latent size) with uORF's decoder instead of light fields (see `volumetric.rs`).
    pub fn volumetric() -> Config {
        Config {
            preset: "volumetric".into(),
            volumetric: Some(VolumetricConfig::uorf()),
            ..Config::small()
        }
    }

    /// A preset by name.
    pub fn preset(name: &str) -> Result<Config> {
        match name {
            "small" => Ok(Config::small()),
            "paper" => Ok(Config::paper()),
            "volumetric" => Ok(Config::volumetric()),
            other => bail!("unknown preset `{other}` (known: small, paper, volumetric)"),
        }
    }

    /// True when slots are decoded by the volumetric baseline instead of light fields.
    pub fn is_volumetric(&self) -> bool {
        self.volumetric.is_some()
    }

    /// The encoding used when the caller does not choose: `inference` if the model has it, else
    /// one pass with `default_slots`.
    pub fn default_inference(&self) -> InferenceConfig {
        self.inference
            .unwrap_or(InferenceConfig::one_pass(self.default_slots))
    }

    /// The length that divides the Plücker moments of field `field`'s lines (0: the
    /// background, whose frame is the world; k ≥ 1: foreground slot k − 1): `scene_scale`, or
    /// `slot_scale` for a foreground slot when set.
    pub fn line_scale(&self, field: usize) -> f64 {
        if field > 0 && self.slot_scale > 0.0 {
            self.slot_scale
        } else {
            self.scene_scale
        }
    }

    /// With `shadow_reach` = ρ: the largest squared bounded moment |m̂|² of a shadow line that
    /// is evaluated ([`Config::reach_bound`]). None: every shadow line is evaluated.
    pub fn shadow_reach_bound(&self) -> Option<f32> {
        self.shadow_light
            .and_then(|_| self.reach_bound(self.shadow_reach))
    }

    /// With `slot_reach` = ρ: the largest squared bounded moment |m̂|² of a camera ray on which
    /// a foreground slot is evaluated ([`Config::reach_bound`]). None: every slot on every ray.
    pub fn slot_reach_bound(&self) -> Option<f32> {
        self.reach_bound(self.slot_reach)
    }

    /// The largest squared bounded moment |m̂|² of a line within `reach` (> 0) of a foreground
    /// frame's origin. The encoding stores m̂ = (m/s)/√(1 + |m/s|²), |m| the line's distance
    /// from the frame origin and s a foreground slot's [`Config::line_scale`] (`rays.rs`), so
    /// |m| ≤ ρ ⟺ |m̂|² ≤ (ρ/s)²/(1 + (ρ/s)²). None for a reach of 0 (no bound).
    fn reach_bound(&self, reach: f64) -> Option<f32> {
        (reach > 0.0).then(|| {
            // (ρ/s)²/(1 + (ρ/s)²) written so that a huge reach gives 1 (every line), not ∞/∞.
            let inverse = (self.line_scale(1) / reach).powi(2);
            (1.0 / (1.0 + inverse)) as f32
        })
    }

    /// Applies `key=value` overrides (the value is JSON, or else a bare string) to this config,
    /// for experiments and recipes: `ray_fourier_freqs=6`, `zero_background=true`, and one
    /// member of a setting that is an object, `inference.refine_mask=0.3` (the rest of it kept;
    /// the setting must be there). Unknown keys and ill-typed values are refused, and the
    /// result is validated.
    pub fn with_overrides(&self, overrides: &[String]) -> Result<Config> {
        if overrides.is_empty() {
            return Ok(self.clone());
        }
        let mut value = serde_json::to_value(self).expect("config serialises");
        let object = value.as_object_mut().expect("config is an object");
        for item in overrides {
            let (key, text) = item
                .split_once('=')
                .with_context(|| format!("config override `{item}` is not KEY=VALUE"))?;
            let key = key.trim();
            let parsed = serde_json::from_str(text.trim())
                .unwrap_or_else(|_| serde_json::Value::String(text.trim().to_string()));
            match key.split_once('.') {
                None => {
                    object.insert(key.to_string(), parsed);
                }
                Some((setting, member)) => {
                    match object.get_mut(setting) {
                        Some(serde_json::Value::Object(members)) => {
                            members.insert(member.to_string(), parsed);
                        }
                        Some(serde_json::Value::Null) | None => bail!(
                            "config override `{key}`: this model has no `{setting}` to change; set it whole, `{setting}={{…}}`"
                        ),
                        Some(_) => bail!(
                            "config override `{key}`: `{setting}` is a value, not a setting with members"
                        ),
                    }
                }
            }
        }
        let cfg: Config =
            serde_json::from_value(value).map_err(|e| anyhow::anyhow!("config override: {e}"))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Parses and validates a config stored in a checkpoint.
    pub fn from_json(text: &str) -> Result<Config> {
        let cfg: Config = serde_json::from_str(text).context("invalid model config")?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// The config as compact JSON (field order fixed by the struct, so it is deterministic).
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("config serialises")
    }

    /// Checks that every size is usable.
    pub fn validate(&self) -> Result<()> {
        let positive = [
            ("encoder_size", self.encoder_size),
            ("encoder_channels", self.encoder_channels),
            ("encoder_channels_low", self.encoder_channels_low),
            ("feature_dim", self.feature_dim),
            ("slot_dim", self.slot_dim),
            ("slot_iters", self.slot_iters),
            ("slot_mlp_hidden", self.slot_mlp_hidden),
            ("lfn_hidden", self.lfn_hidden),
            ("lfn_features", self.lfn_features),
            ("hypernet_hidden", self.hypernet_hidden),
            ("head_hidden", self.head_hidden),
            ("compositor_hidden", self.compositor_hidden),
        ];
        for (name, value) in positive {
            if value == 0 {
                bail!("model config: `{name}` must be positive");
            }
        }
        if !matches!(self.encoder_first_stride, 1 | 2) {
            bail!("model config: `encoder_first_stride` must be 1 or 2");
        }
        let grid = self.encoder_size / self.encoder_first_stride;
        if !self
            .encoder_size
            .is_multiple_of(4 * self.encoder_first_stride)
            || grid < 4
        {
            bail!(
                "model config: `encoder_size` {} must be a multiple of {} (two stride-2 layers)",
                self.encoder_size,
                4 * self.encoder_first_stride
            );
        }
        if self.encoder_size > 1024 || self.ray_fourier_freqs > 16 || self.lfn_hidden_layers > 16 {
            bail!("model config: a size is implausibly large");
        }
        if !(self.frame_ground_height.is_finite() && self.frame_ground_height >= 0.0) {
            bail!("model config: `frame_ground_height` must be a non-negative number");
        }
        if !(self.cull_behind.is_finite() && self.cull_behind >= 0.0) {
            bail!("model config: `cull_behind` must be a non-negative number");
        }
        if self.frames_from_residual && !(self.attention_frames && self.static_background) {
            bail!("model config: `frames_from_residual` places attention frames (`attention_frames`) against a static background (`static_background`): set both");
        }
        if self.frame_ground_contact && self.frame_ground_height > 0.0 {
            bail!("model config: `frame_ground_contact` and `frame_ground_height` both place frames on the ground: set one");
        }
        if !(self.fg_locality.is_finite() && self.fg_locality >= 0.0) {
            bail!("model config: `fg_locality` must be a non-negative number");
        }
        if !(self.scene_scale.is_finite() && self.scene_scale > 0.0) {
            bail!("model config: `scene_scale` must be a positive number");
        }
        if !(self.slot_scale.is_finite() && self.slot_scale >= 0.0) {
            bail!("model config: `slot_scale` must be a length ≥ 0 (0: `scene_scale`)");
        }
        if self.static_background && !self.zero_background {
            bail!("model config: `static_background` needs `zero_background` (an image-dependent background needs its hypernetwork)");
        }
        if self.background_reader && (self.zero_background || self.is_volumetric()) {
            bail!("model config: `background_reader` needs a light-field model with an image-dependent background (`zero_background` off)");
        }
        if let Some([azimuth, elevation]) = self.shadow_light {
            if !self.shadow_head {
                bail!("model config: `shadow_light` needs `shadow_head`");
            }
            if !(azimuth.is_finite() && elevation > 0.0 && elevation <= 90.0) {
                bail!("model config: `shadow_light` must be [azimuth, elevation] in degrees with 0 < elevation ≤ 90");
            }
        }
        if self.shadow_reach != 0.0
            && !(self.shadow_reach.is_finite()
                && self.shadow_reach > 0.0
                && self.shadow_light.is_some())
        {
            bail!("model config: `shadow_reach` must be a positive distance, and needs `shadow_light`");
        }
        if self.slot_reach != 0.0
            && !(self.slot_reach.is_finite() && self.slot_reach > 0.0 && !self.is_volumetric())
        {
            bail!("model config: `slot_reach` must be a positive distance, and applies to light-field models only");
        }
        if self.floor_fourier_freqs > MAX_FLOOR_FOURIER_FREQS {
            bail!(
                "model config: `floor_fourier_freqs` is at most {MAX_FLOOR_FOURIER_FREQS} (asked: {})",
                self.floor_fourier_freqs
            );
        }
        if self.floor_fourier_freqs > 0 && self.is_volumetric() {
            bail!("model config: `floor_fourier_freqs` applies to light-field models, not the volumetric baseline");
        }
        if let Some(v) = &self.volumetric {
            if self.shadow_head {
                bail!("model config: `shadow_head` applies to light-field models, not the volumetric baseline");
            }
            if self.slot_scale > 0.0 {
                bail!("model config: `slot_scale` applies to light-field models, not the volumetric baseline");
            }
            v.validate()?;
        }
        if let Some(inference) = &self.inference {
            if !(1..=MAX_ENCODE_SLOTS).contains(&inference.slots)
                || !(1..=MAX_ENCODE_TRIES).contains(&inference.tries)
                || inference.refine > MAX_INFERENCE_REFINE
            {
                bail!("model config: `inference` needs 1 ≤ slots ≤ {MAX_ENCODE_SLOTS}, 1 ≤ tries ≤ {MAX_ENCODE_TRIES} and refine ≤ {MAX_INFERENCE_REFINE}");
            }
            let rate_ok = |lr: Option<f64>, zero_ok: bool| {
                lr.is_none_or(|lr| {
                    lr.is_finite() && (lr > 0.0 || (zero_ok && lr == 0.0)) && lr <= MAX_REFINE_LR
                })
            };
            if !rate_ok(inference.refine_lr, false) || !rate_ok(inference.refine_frame_lr, true) {
                bail!("model config: `inference` needs refine_lr in (0, {MAX_REFINE_LR}] and refine_frame_lr in [0, {MAX_REFINE_LR}]");
            }
            if inference
                .refine_rays
                .is_some_and(|r| !(1..=MAX_INFERENCE_REFINE_RAYS).contains(&r))
            {
                bail!(
                    "model config: `inference` needs 1 ≤ refine_rays ≤ {MAX_INFERENCE_REFINE_RAYS}"
                );
            }
            if inference
                .refine_mask
                .is_some_and(|w| !(w.is_finite() && w >= 0.0))
                || inference
                    .refine_mask_claim
                    .is_some_and(|c| c > MAX_INFERENCE_MASK_CLAIM)
            {
                bail!("model config: `inference` needs refine_mask ≥ 0 and refine_mask_claim ≤ {MAX_INFERENCE_MASK_CLAIM}");
            }
            if inference.refine_mask.is_some_and(|w| w > 0.0) && !self.static_background {
                bail!("model config: `inference.refine_mask` needs a static background (`static_background`): the proposals are made against its render");
            }
            if self.volumetric.is_some() && inference.refine > 0 {
                bail!("model config: `inference.refine` applies to light-field models, not the volumetric baseline");
            }
        }
        Ok(())
    }

    /// Side of the token grid (tokens = grid²).
    pub fn token_grid(&self) -> usize {
        self.encoder_size / self.encoder_first_stride
    }

    /// Input size of a light field: 6 Plücker coordinates, plus sin/cos per frequency, plus
    /// the floor columns ([`Config::floor_input_dim`]). One width for every field: the
    /// foreground slots' floor columns are zeros.
    pub fn ray_input_dim(&self) -> usize {
        self.line_input_dim() + self.floor_input_dim()
    }

    /// The columns of a light field's input that encode the line: 6 Plücker coordinates, plus
    /// sin/cos per frequency (`ray_fourier_freqs`). The floor columns follow them.
    pub fn line_input_dim(&self) -> usize {
        6 * (1 + 2 * self.ray_fourier_freqs)
    }

    /// The floor columns at the end of a light field's input (`floor_fourier_freqs` = L): none
    /// when L = 0, else a hit flag, the bounded hit point (x, y) and sin/cos of x and y at L
    /// octaves, 3 + 4·L.
    pub fn floor_input_dim(&self) -> usize {
        floor_columns(self.floor_fourier_freqs)
    }

    /// The heads' MLPs: (hidden width, hidden layers).
    pub fn head_shape(&self) -> (usize, usize) {
        (self.head_hidden, self.head_hidden_layers)
    }

    /// The compositor's V: (hidden width, hidden layers).
    pub fn compositor_shape(&self) -> (usize, usize) {
        (self.compositor_hidden, self.compositor_hidden_layers)
    }

    /// Layer widths of a light-field MLP, input first.
    pub fn lfn_dims(&self) -> Vec<usize> {
        let mut dims = vec![self.ray_input_dim()];
        dims.extend(std::iter::repeat_n(self.lfn_hidden, self.lfn_hidden_layers));
        dims.push(self.lfn_features);
        dims
    }
}

/// The floor columns for `freqs` octaves ([`Config::floor_input_dim`]).
pub fn floor_columns(freqs: usize) -> usize {
    if freqs == 0 {
        0
    } else {
        3 + 4 * freqs
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_validate_and_round_trip() {
        for cfg in [Config::small(), Config::paper()] {
            cfg.validate().unwrap();
            assert_eq!(Config::from_json(&cfg.to_json()).unwrap(), cfg);
        }
        assert_eq!(Config::small().lfn_dims(), vec![6, 128, 128, 32]);
        assert_eq!(Config::paper().lfn_dims(), vec![6, 256, 256, 64]);
        assert_eq!(Config::small().token_grid(), 32);
    }

    #[test]
    fn volumetric_preset_round_trips_and_light_field_json_is_unchanged() {
        let cfg = Config::volumetric();
        cfg.validate().unwrap();
        assert_eq!(Config::from_json(&cfg.to_json()).unwrap(), cfg);
        assert_eq!(cfg.volumetric.as_ref().unwrap().pos_dim(), 33);
        assert!(!Config::small().to_json().contains("volumetric"));
        let mut bad = Config::volumetric();
        bad.volumetric.as_mut().unwrap().far = 1.0;
        assert!(bad.validate().is_err());
        let json = cfg
            .to_json()
            .replace("\"samples\"", "\"mystery\":1,\"samples\"");
        assert!(Config::from_json(&json).is_err());
    }

    #[test]
    fn inference_defaults_are_optional_validated_and_set_by_override() {
        let small = Config::small();
        assert!(
            !small.to_json().contains("inference"),
            "older identities unchanged"
        );
        assert_eq!(small.default_inference(), InferenceConfig::one_pass(7));
        let cfg = small
            .with_overrides(&[r#"inference={"slots":12,"tries":4,"refine":50}"#.into()])
            .unwrap();
        let measured = InferenceConfig {
            slots: 12,
            tries: 4,
            refine: 50,
            refine_lr: None,
            refine_frame_lr: None,
            refine_rays: None,
            refine_mask: None,
            refine_mask_claim: None,
        };
        assert_eq!(cfg.default_inference(), measured);
        assert!(!cfg.to_json().contains("refine_lr"), "identities unchanged");
        assert_eq!(Config::from_json(&cfg.to_json()).unwrap(), cfg);
        // `null` removes them again.
        assert_eq!(
            cfg.with_overrides(&["inference=null".into()]).unwrap(),
            small
        );
        for bad in [
            r#"inference={"slots":0,"tries":1,"refine":0}"#,
            r#"inference={"slots":7,"tries":0,"refine":0}"#,
            r#"inference={"slots":7,"tries":101,"refine":0}"#,
            r#"inference={"slots":7,"tries":1,"refine":1000000}"#,
            r#"inference={"slots":7,"tries":1}"#,
            r#"inference={"slots":7,"tries":1,"refine":0,"lr":1}"#,
            r#"inference={"slots":7,"tries":1,"refine":9,"refine_lr":0}"#,
            r#"inference={"slots":7,"tries":1,"refine":9,"refine_lr":-0.01}"#,
            r#"inference={"slots":7,"tries":1,"refine":9,"refine_lr":1000}"#,
            r#"inference={"slots":7,"tries":1,"refine":9,"refine_frame_lr":-1}"#,
            r#"inference={"slots":7,"tries":1,"refine":9,"refine_rays":0}"#,
            r#"inference={"slots":7,"tries":1,"refine":9,"refine_rays":2000000}"#,
            r#"inference={"slots":7,"tries":1,"refine":9,"refine_mask":-1}"#,
            r#"inference={"slots":7,"tries":1,"refine":9,"refine_mask":1}"#,
            r#"inference={"slots":7,"tries":1,"refine":9,"refine_mask_claim":65}"#,
        ] {
            assert!(small.with_overrides(&[bad.into()]).is_err(), "{bad}");
        }
        // A static background may carry refinement's mask loss.
        let city = small
            .with_overrides(&[
                "static_background=true".into(),
                "zero_background=true".into(),
                r#"inference={"slots":7,"tries":1,"refine":9,"refine_mask":1,"refine_mask_claim":3}"#
                    .into(),
            ])
            .unwrap();
        let inference = city.default_inference();
        assert_eq!(
            (inference.refine_mask, inference.refine_mask_claim),
            (Some(1.0), Some(3))
        );
        // One member is set alone, the others kept; and only where the setting is there.
        let with_mask = city
            .with_overrides(&["inference.refine_mask=0.3".into()])
            .unwrap();
        let inference = with_mask.default_inference();
        assert_eq!(
            (
                inference.slots,
                inference.refine_mask,
                inference.refine_mask_claim
            ),
            (7, Some(0.3), Some(3))
        );
        for bad in [
            "inference.refine_mask=-1",
            "inference.no_such_member=1",
            "inference.slots=many",
        ] {
            assert!(city.with_overrides(&[bad.into()]).is_err(), "{bad}");
        }
        let unset = format!(
            "{:#}",
            small
                .with_overrides(&["inference.refine=50".into()])
                .unwrap_err()
        );
        assert!(unset.contains("no `inference` to change"), "{unset}");
        assert!(small
            .with_overrides(&["lfn_hidden.width=3".into()])
            .is_err());
        // Measured learning rates ride along, and a fixed frame (0) is allowed.
        let rates = small
            .with_overrides(&[
                r#"inference={"slots":12,"tries":4,"refine":25,"refine_lr":0.02,"refine_frame_lr":0}"#
                    .into(),
            ])
            .unwrap();
        let inference = rates.default_inference();
        assert_eq!(
            (inference.refine_lr, inference.refine_frame_lr),
            (Some(0.02), Some(0.0))
        );
        assert_eq!(Config::from_json(&rates.to_json()).unwrap(), rates);
        // So does the pixels a step renders.
        let rays = small
            .with_overrides(&[
                r#"inference={"slots":12,"tries":2,"refine":25,"refine_rays":512}"#.into(),
            ])
            .unwrap();
        assert_eq!(rays.default_inference().refine_rays, Some(512));
        assert_eq!(Config::from_json(&rays.to_json()).unwrap(), rays);
        // The volumetric baseline cannot be refined.
        let volumetric = Config::volumetric();
        assert!(volumetric
            .with_overrides(&[r#"inference={"slots":7,"tries":2,"refine":5}"#.into()])
            .is_err());
        assert!(volumetric
            .with_overrides(&[r#"inference={"slots":7,"tries":2,"refine":0}"#.into()])
            .is_ok());
    }

    #[test]
    fn bad_configs_are_refused() {
        let mut cfg = Config::small();
        cfg.encoder_size = 66;
        assert!(cfg.validate().is_err());
        let mut cfg = Config::small();
        cfg.scene_scale = f64::NAN;
        assert!(cfg.validate().is_err());
        let mut cfg = Config::small();
        cfg.frame_ground_contact = true;
        assert!(cfg.validate().is_ok());
        cfg.frame_ground_height = 0.5;
        assert!(format!("{:#}", cfg.validate().unwrap_err()).contains("set one"));
        let json = Config::small()
            .to_json()
            .replace("\"slot_dim\"", "\"mystery\":1,\"slot_dim\"");
        assert!(Config::from_json(&json).is_err());
        assert!(Config::preset("huge").is_err());
    }

    #[test]
    fn overrides_change_named_fields_and_refuse_unknown_ones() {
        let cfg = Config::small()
            .with_overrides(&["ray_fourier_freqs=4".into(), "zero_background=true".into()])
            .unwrap();
        assert_eq!(cfg.ray_fourier_freqs, 4);
        assert!(cfg.zero_background);
        assert_eq!(cfg.lfn_hidden, Config::small().lfn_hidden);
        assert!(Config::small()
            .with_overrides(&["no_such_knob=1".into()])
            .is_err());
        assert!(Config::small()
            .with_overrides(&["lfn_hidden=wide".into()])
            .is_err());
        assert!(Config::small()
            .with_overrides(&["lfn_hidden".into()])
            .is_err());
        assert!(Config::small()
            .with_overrides(&["slot_dim=0".into()])
            .is_err());
    }
    /// The reach's bound on the encoded moment: the distance it stands for at ordinary reaches,
    /// every line at a huge one, none but the origin's at a tiny one; refused without a light,
    /// negative or not finite; absent from the JSON when 0, so older models keep their bytes.
    #[test]
    fn shadow_reach_bounds_the_encoded_moment_at_every_scale() {
        let lit = Config::small()
            .with_overrides(&["shadow_head=true".into(), "shadow_light=[30, 55]".into()])
            .unwrap();
        assert_eq!(lit.shadow_reach_bound(), None);
        assert!(!lit.to_json().contains("shadow_reach"));
        let with = |reach: f64| Config {
            shadow_reach: reach,
            ..lit.clone()
        };
        // |m̂| = (ρ/s)/√(1 + (ρ/s)²) at the reach itself.
        let q = with(3.0).shadow_reach_bound().unwrap() as f64;
        let r = 3.0 / lit.scene_scale;
        assert!((q - r * r / (1.0 + r * r)).abs() < 1e-7);
        // With the slots' own line scale, at that scale (the line's moment in a slot's frame).
        let scaled = Config {
            slot_scale: 1.5,
            ..with(3.0)
        };
        let q = scaled.shadow_reach_bound().unwrap() as f64;
        assert!((q - 4.0 / 5.0).abs() < 1e-7, "{q}");
        for bad in [-1.0, f64::NAN, f64::INFINITY] {
            let cfg = Config {
                slot_scale: bad,
                ..Config::small()
            };
            assert!(cfg.validate().is_err(), "{bad}");
        }
        assert!(!Config::small().to_json().contains("slot_scale"));
        let volumetric = Config {
            slot_scale: 1.5,
            ..Config::volumetric()
        };
        assert!(volumetric.validate().is_err());
        assert_eq!(with(1e300).shadow_reach_bound(), Some(1.0));
        assert_eq!(with(1e-300).shadow_reach_bound(), Some(0.0));
        for bad in [-1.0, f64::NAN, f64::INFINITY] {
            assert!(with(bad).validate().is_err(), "{bad}");
        }
        let dark = Config {
            shadow_reach: 3.0,
            ..Config::small()
        };
        assert!(dark.validate().is_err());
        assert!(with(3.0).validate().is_ok());
    }

    /// The slots' own reach bounds camera rays as the shadow reach bounds shadow lines, with
    /// or without shadows; refused when negative, not finite or on a volumetric model; absent
    /// from the JSON when 0.
    #[test]
    fn slot_reach_bounds_the_encoded_moment_of_camera_rays() {
        let small = Config::small();
        assert_eq!(small.slot_reach_bound(), None);
        assert!(!small.to_json().contains("slot_reach"));
        let with = |reach: f64| Config {
            slot_reach: reach,
            ..Config::small()
        };
        let q = with(3.0).slot_reach_bound().unwrap() as f64;
        let r = 3.0 / small.scene_scale;
        assert!((q - r * r / (1.0 + r * r)).abs() < 1e-7);
        assert_eq!(with(3.0).shadow_reach_bound(), None);
        assert!(with(3.0).validate().is_ok());
        assert!(with(3.0).to_json().contains("\"slot_reach\":3.0"));
        for bad in [-1.0, f64::NAN, f64::INFINITY] {
            assert!(with(bad).validate().is_err(), "{bad}");
        }
        let volumetric = Config {
            slot_reach: 3.0,
            ..Config::volumetric()
        };
        assert!(volumetric.validate().is_err());
    }

    /// Floor features widen the input by 3 + 4·L and nothing else; a config without them writes
    /// no key (older files keep their JSON and identity), one with them round-trips; more than
    /// the cap, or on a volumetric model, is refused.
    #[test]
    fn floor_fourier_freqs_widen_the_input_and_are_absent_from_json_when_off() {
        let small = Config::small();
        assert_eq!(small.floor_input_dim(), 0);
        assert!(!small.to_json().contains("floor_fourier_freqs"));
        // An older file's JSON (without the key) reads back to the same config and JSON.
        let json = small.to_json();
        let read = Config::from_json(&json).unwrap();
        assert_eq!(read, small);
        assert_eq!(read.to_json(), json);
        let floor = small
            .with_overrides(&["floor_fourier_freqs=5".into()])
            .unwrap();
        assert_eq!(floor.floor_fourier_freqs, 5);
        assert_eq!(floor.floor_input_dim(), 23);
        assert_eq!(floor.lfn_dims(), vec![6 + 23, 128, 128, 32]);
        let both = Config {
            ray_fourier_freqs: 2,
            ..floor.clone()
        };
        assert_eq!(both.line_input_dim(), 30);
        assert_eq!(both.ray_input_dim(), 30 + 23);
        assert!(floor.to_json().contains("\"floor_fourier_freqs\":5"));
        assert_eq!(Config::from_json(&floor.to_json()).unwrap(), floor);
        assert!(small
            .with_overrides(&[format!(
                "floor_fourier_freqs={}",
                MAX_FLOOR_FOURIER_FREQS + 1
            )])
            .is_err());
        assert!(small
            .with_overrides(&[format!("floor_fourier_freqs={MAX_FLOOR_FOURIER_FREQS}")])
            .is_ok());
        let volumetric = Config {
            floor_fourier_freqs: 2,
            ..Config::volumetric()
        };
        assert!(volumetric.validate().is_err());
    }
}
