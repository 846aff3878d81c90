//! The training loop: batches of scenes, one encoded view each, novel and input views
//! supervised on random rays; Adam; JSON-lines log; atomic, exactly-resumable checkpoints.
//!
//! Every step draws its randomness from `StdRng::seed_from_u64(mix(seed, step))`, so a run
//! resumed from a checkpoint at step N takes exactly the steps an uninterrupted run would have.

use super::batch::{sample_scene, InputView, MaskExclusion, RaySampling, SceneSample};
use super::known_background::{view_proposals, KnownBackground};
use crate::dataset::{Dataset, SceneData};
use crate::model::checkpoint::{self, HostParams};
use crate::model::encoder::image_tensor;
use crate::model::grow::{Growth, SlotValues};
use crate::model::history::{self, TrainingRun};
use crate::model::{Colf, Config, Decoded, RayBatch, SceneRays, SlotOutput};
use crate::optim::{Adam, AdamConfig};
use crate::proposals::{is_instance, ProposalParams};
use crate::tensorfile::{serialize_f32, F32Tensor, TensorFile};
use anyhow::{anyhow, bail, Context, Result};
use candle_core::{DType, Tensor, D};
use glam::DMat4;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// The learning rate of step `step`: linear warm-up over `opts.warmup` steps, then constant, or,
/// from `opts.decay_from` on, a half cosine from `opts.lr` down to `opts.final_lr` at `opts.steps`.
pub fn learning_rate(opts: &TrainOptions, step: u64) -> f64 {
    let warm = opts.warmup.max(1) as f64;
    let warmed = opts.lr * ((step + 1) as f64 / warm).min(1.0);
    match opts.decay_from {
        Some(start) if step >= start && opts.steps > start => {
            let progress = ((step - start) as f64 / (opts.steps - start) as f64).min(1.0);
            let cosine = 0.5 * (1.0 + (std::f64::consts::PI * progress).cos());
            opts.final_lr + (warmed - opts.final_lr) * cosine
        }
        _ => warmed,
    }
}

/// Everything a training run is configured by (stored in its checkpoints).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct TrainOptions {
    /// Training data (colf or uORF layout).
    pub data: PathBuf,
    /// Model file written at every checkpoint and at the end.
    pub out: PathBuf,
    /// Start from this model (curriculum); else a fresh `preset` model.
    pub init: Option<PathBuf>,
    pub preset: String,
    /// Total steps (a resumed run continues up to this).
    pub steps: u64,
    /// Scenes per batch.
    pub batch_scenes: usize,
    pub views_per_scene: usize,
    /// The views every scene encodes together (its context views: slots of all of them make
    /// the scene's); empty: one random view.
    #[serde(default)]
    pub context_views: Vec<usize>,
    pub rays_per_view: usize,
    /// Foreground slots (default: the model's).
    pub slots: Option<usize>,
    pub lr: f64,
    /// Linear learning-rate warm-up steps.
    pub warmup: u64,
    /// Cosine decay of the learning rate from `lr` at this step to `final_lr` at `steps`
    /// (None: constant after the warm-up). A step, not a fraction, so that a run resumed with a
    /// larger `steps` keeps the rates it already used.
    #[serde(default)]
    pub decay_from: Option<u64>,
    /// Learning rate reached at `steps` when `decay_from` is set.
    #[serde(default)]
    pub final_lr: f64,
    pub l1_weight: f64,
    /// Weight of the mean squared foreground latent.
    pub latent_weight: f64,
    /// Weak supervision from ground-truth masks (Hungarian-matched slots); 0 = unsupervised.
    pub mask_weight: f64,
    /// Weak supervision of the slot attention by the input view's mask (0 = none).
    #[serde(default)]
    pub attention_mask_weight: f64,
    /// Share of rays drawn from object pixels (uses masks).
    pub object_fraction: f64,
    /// Mask losses ignore background pixels (rays and tokens) within this many pixels of an
    /// object: masks call an object's shadow background, but a background that cannot depend on
    /// the image cannot draw it, so only the object's slot can.
    #[serde(default)]
    pub mask_margin: usize,
    /// The mask losses on rays count an unsure proposal pixel within this many pixels of an
    /// instance to that instance (`proposals::claimed_instance`): its soft edge (0 = off).
    #[serde(default)]
    pub mask_claim: usize,
    /// Mask losses also ignore background pixels darker than their view's floor by more than
    /// this (0 = off; see `batch::shadow_threshold`).
    #[serde(default)]
    pub mask_shadow_depth: f64,
    /// Fresh models only: render the background from a zero latent, so it cannot depend on the
    /// image (the paper's choice for CLEVR); stored in the model's config.
    pub zero_background: bool,
    /// Fresh models only: KEY=VALUE overrides of the preset's config.
    #[serde(default)]
    pub config_overrides: Vec<String>,
    /// With `init` and a wider `slot_dim` among the overrides: copies of the old values or
    /// fresh ones (`model::grow`).
    #[serde(default)]
    pub slot_values: SlotValues,
    pub seed: u64,
    pub checkpoint_every: u64,
    /// Also keep a copy of the model file every this many steps (0: never), named by
    /// `snapshot_path`, so a run that later degrades can be rewound to its best step.
    #[serde(default)]
    pub keep_every: u64,
    /// Evaluate on `eval_data` every this many steps (0: never).
    pub eval_every: u64,
    pub eval_data: Option<PathBuf>,
    pub eval_scenes: usize,
    /// Abort after this many non-finite steps.
    pub max_bad_steps: u64,
    /// Use only the first N training scenes (overfitting tests).
    pub max_scenes: Option<usize>,
    /// Object proposals computed from each training image ([`crate::proposals`]) stand in for
    /// masks: mask files are never opened, and the mask losses and the sampling of rays on
    /// objects use the proposals (ids local to each view).
    #[serde(default)]
    pub proposals: bool,
    /// With `proposals`: propose objects against this model's background, rendered alone at
    /// each view's camera ([`super::known_background`]), instead of against a fitted floor.
    #[serde(default)]
    pub proposals_against: Option<PathBuf>,
    /// Parameters whose names start with one of these are not updated (e.g. `encoder.` and
    /// `slot_attention.`, to adapt the decoder to a new look while keeping how slots group).
    #[serde(default)]
    pub freeze: Vec<String>,
    /// (prefix, factor): parameters whose names start with the prefix learn at `factor` times
    /// the schedule's rate (a later pair wins where prefixes overlap).
    #[serde(default)]
    pub lr_scale: Vec<(String, f64)>,
    /// Decode through candle's autograd (`ColfNet::decode_reference`) instead of the fused
    /// kernel: the same function, several times slower; for checking the kernel on a real run.
    #[serde(default)]
    pub reference_decoder: bool,
}

impl TrainOptions {
    /// Checkpoint path: `<out>.ckpt`.
    pub fn checkpoint_path(&self) -> PathBuf {
        let mut p = self.out.clone().into_os_string();
        p.push(".ckpt");
        PathBuf::from(p)
    }

    /// Kept model of `step`: `<out>` with `.step<N>` before its `.safetensors` extension
    /// (`m.safetensors` → `m.step2000.safetensors`), or appended when it has none.
    pub fn snapshot_path(&self, step: u64) -> PathBuf {
        let name = self.out.file_name().unwrap_or_default().to_string_lossy();
        let kept = match name.strip_suffix(".safetensors") {
            Some(stem) => format!("{stem}.step{step}.safetensors"),
            None => format!("{name}.step{step}"),
        };
        self.out.with_file_name(kept)
    }

    /// JSON-lines log path: `<out>.log.jsonl`.
    pub fn log_path(&self) -> PathBuf {
        let mut p = self.out.clone().into_os_string();
        p.push(".log.jsonl");
        PathBuf::from(p)
    }

    fn validate(&self) -> Result<()> {
        if self.batch_scenes == 0 || self.views_per_scene == 0 || self.rays_per_view == 0 {
            bail!("batch size, views per scene and rays per view must be positive");
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            bail!("learning rate must be positive");
        }
        for (name, v) in [
            ("l1 weight", self.l1_weight),
            ("latent weight", self.latent_weight),
            ("mask weight", self.mask_weight),
            ("attention mask weight", self.attention_mask_weight),
        ] {
            if !(v >= 0.0 && v.is_finite()) {
                bail!("{name} must be a non-negative number");
            }
        }
        if !(0.0..=1.0).contains(&self.object_fraction) {
            bail!("object fraction must be in [0, 1]");
        }
        if !(0.0..=1.0).contains(&self.mask_shadow_depth) {
            bail!("the mask shadow depth must be in [0, 1]");
        }
        if !self.context_views.is_empty() {
            if let Some(error) = crate::evaluate::input_views_error(&self.context_views) {
                bail!("context views: {error}");
            }
        }
        if self.views_per_scene < self.context_views.len() {
            bail!(
                "{} views supervised per scene cannot include the {} context views",
                self.views_per_scene,
                self.context_views.len()
            );
        }
        if self.proposals_against.is_some() && !self.proposals {
            bail!("proposals against a known background need proposals");
        }
        if self.mask_claim > 0 && !self.proposals {
            bail!("claiming the proposals' unsure edges (--mask-claim) needs --proposals");
        }
        Ok(())
    }
}

/// One line of the training log.
#[derive(Clone, Debug, Default, Serialize)]
pub struct StepLog {
    pub step: u64,
    pub loss: f64,
    pub mse: f64,
    /// PSNR of the sampled rays (dB).
    pub psnr: f64,
    /// PSNR of the sampled rays that hit a ground-truth object.
    pub obj_psnr: Option<f64>,
    /// Mean foreground weight on object rays: how much of the objects the slots won.
    pub fg_share: Option<f64>,
    /// ARI between argmax slots and object ids on object rays, averaged over scenes.
    pub fg_ari: Option<f64>,
    /// Foreground slots that win at least one sampled ray, averaged over scenes.
    pub slots_used: f64,
    pub mask_loss: Option<f64>,
    /// Cross-entropy of the slot attention against the input view's mask (when supervised).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub attention_mask_loss: Option<f64>,
    pub lr: f64,
    pub grad_norm: f64,
    pub rays_per_s: f64,
    pub seconds: f64,
    /// Where the step's time went: data + forward pass + loss, backward pass, optimizer update.
    pub forward_s: f64,
    pub backward_s: f64,
    pub update_s: f64,
    /// Of the forward and backward passes, the time in the decode kernel (0 with
    /// `--reference-decoder`): what is left of a step when the decoder is taken out.
    pub decoder_s: f64,
    pub skipped: bool,
}

/// The state of a run.
pub struct Trainer {
    pub opts: TrainOptions,
    colf: Colf,
    adam: Adam,
    data: Vec<SceneData>,
    eval_data: Option<Dataset>,
    pub step: u64,
    pub bad_steps: u64,
    num_slots: usize,
    /// The training records of the model this run started from, and this run's own record
    /// (its `steps` set when a model file is written).
    earlier_runs: Vec<TrainingRun>,
    this_run: TrainingRun,
}

/// What a step's forward pass computed.
struct Forward {
    encoded: SlotOutput,
    decoded: Decoded,
    /// The rays' target colours, RGB per ray, scene-major.
    targets: Vec<f32>,
    /// The compositor weights on the host, [B, R, S] flattened.
    weights_host: Vec<f32>,
}

const CHECKPOINT_FORMAT: &str = "colf-train-checkpoint/1";

fn step_rng(seed: u64, step: u64) -> StdRng {
    // splitmix-style mixing so neighbouring steps get unrelated streams.
    let mut z = seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    StdRng::seed_from_u64(z ^ (z >> 31))
}

/// The first `max` scenes of the training data; with `proposals`, their mask files are never
/// read, and each view's mask is its object proposals instead.
/// With `against`, the proposals are made against that model's background render.
fn load_scenes(
    path: &Path,
    max: Option<usize>,
    proposals: bool,
    against: Option<&Path>,
) -> Result<Vec<SceneData>> {
    let mut data = Dataset::open(path)?;
    if data.is_empty() {
        bail!("{}: no scenes found", path.display());
    }
    if proposals {
        data = data.without_masks();
    }
    let n = max.map_or(data.len(), |m| m.min(data.len()));
    let params = ProposalParams::default();
    let known = against.map(KnownBackground::load).transpose()?;
    (0..n)
        .map(|i| {
            let mut scene = data.load(i)?;
            if proposals {
                for view in &mut scene.views {
                    view.mask = Some(view_proposals(known.as_ref(), view, &params)?);
                }
                scene.view_local_ids = true;
            }
            Ok(scene)
        })
        .collect()
}

impl Trainer {
    /// A new run, or (`resume`) the run saved in `opts.checkpoint_path()`.
    pub fn new(opts: TrainOptions, resume: bool) -> Result<Trainer> {
        opts.validate()?;
        let data = load_scenes(
            &opts.data,
            opts.max_scenes,
            opts.proposals,
            opts.proposals_against.as_deref(),
        )?;
        if let Some(&last) = opts.context_views.iter().max() {
            if let Some(scene) = data.iter().find(|s| s.views.len() <= last) {
                bail!(
                    "{}: scene {} has {} views; there is no context view {last}",
                    opts.data.display(),
                    scene.name,
                    scene.views.len()
                );
            }
        }
        let (colf, adam_state, step, bad_steps, earlier_runs, init_identity) = if resume {
            let path = opts.checkpoint_path();
            let bytes = std::fs::read(&path).with_context(|| {
                format!("{}: cannot read the checkpoint to resume", path.display())
            })?;
            let saved = load_checkpoint(&bytes, &path.display().to_string())?;
            let (colf, step, bad) = (saved.colf, saved.step, saved.bad_steps);
            // The checkpoint's records end with this run's; a checkpoint written before
            // records existed has none, and the initial model its options name (if still
            // there) gives them.
            let (earlier, init) = match colf.training().split_last() {
                Some((this, earlier)) => (earlier.to_vec(), this.init.clone()),
                None => match saved.init_path {
                    Some(p) if p.is_file() => {
                        let init = Colf::load(&p)?;
                        (init.training().to_vec(), Some(init.identity()?))
                    }
                    _ => (Vec::new(), None),
                },
            };
            (colf, Some(bytes), step, bad, earlier, init)
        } else {
            let colf = match &opts.init {
                Some(p) => {
                    let colf = Colf::load(p)?;
                    if opts.config_overrides.is_empty() {
                        colf
                    } else {
                        let cfg = colf.config().with_overrides(&opts.config_overrides)?;
                        let growth = Growth {
                            seed: opts.seed,
                            slot_values: opts.slot_values,
                        };
                        colf.grown(&cfg, growth, &p.display().to_string())
                            .context("a config change of an initial model may only keep every tensor's shape or grow the model (static_background, zero_background=false, shadow_head, a wider hypernet_hidden, lfn_hidden or slot_dim, hypernet_per_layer, more floor_fourier_freqs)")?
                    }
                }
                None => {
                    // The flag first, so `--set static_background=true` (which needs it) validates.
                    let mut preset = Config::preset(&opts.preset)?;
                    preset.zero_background |= opts.zero_background;
                    let cfg = preset.with_overrides(&opts.config_overrides)?;
                    Colf::init(&cfg, opts.seed)?
                }
            };
            let (earlier, init) = match &opts.init {
                Some(_) => (colf.training().to_vec(), Some(colf.identity()?)),
                None => (Vec::new(), None),
            };
            (colf, None, 0, 0, earlier, init)
        };
        let this_run = run_record(&opts, &data, init_identity);
        if this_run.masks_used && !this_run.masks_in_data {
            bail!(
                "{}: no training scene has a mask file, and the mask losses or the sampling of \
                 rays on objects need them (train with no mask supervision on unlabelled data)",
                opts.data.display()
            );
        }
        let mut colf = colf.into_trainable()?;
        colf.set_reference_decoder(opts.reference_decoder);
        let vars = colf.named_vars();
        if let Some(prefix) = opts
            .freeze
            .iter()
            .find(|p| !vars.iter().any(|(n, _)| n.starts_with(p.as_str())))
        {
            bail!("no parameter of the model has a name starting with `{prefix}` (to freeze)");
        }
        let trained: Vec<_> = vars
            .into_iter()
            .filter(|(n, _)| !opts.freeze.iter().any(|p| n.starts_with(p.as_str())))
            .collect();
        let mut adam = Adam::new(trained, AdamConfig::default())?;
        for (prefix, factor) in &opts.lr_scale {
            if adam.scale_learning_rate(prefix, *factor)? == 0 {
                bail!(
                    "no trained parameter of the model has a name starting with `{prefix}` \
                     (to scale its learning rate)"
                );
            }
        }
        if let Some(bytes) = adam_state {
            let file = TensorFile::parse(&bytes, "checkpoint")?;
            adam.load_state_tensors(&file, "adam/", step)?;
        }
        let num_slots = opts.slots.unwrap_or(colf.config().default_slots);
        let eval_data = match &opts.eval_data {
            Some(p) if opts.eval_every > 0 => Some(Dataset::open(p)?),
            _ => None,
        };
        Ok(Trainer {
            opts,
            colf,
            adam,
            data,
            eval_data,
            step,
            bad_steps,
            num_slots,
            earlier_runs,
            this_run,
        })
    }

    /// The model's training records as of now: the initial model's, then this run's.
    pub fn training_records(&self) -> Vec<TrainingRun> {
        let mut runs = self.earlier_runs.clone();
        runs.push(TrainingRun {
            steps: self.step,
            ..self.this_run.clone()
        });
        runs
    }

    pub fn model(&self) -> &Colf {
        &self.colf
    }

    pub fn num_scenes(&self) -> usize {
        self.data.len()
    }

    fn learning_rate(&self) -> f64 {
        learning_rate(&self.opts, self.step)
    }

    /// One optimisation step (a non-finite loss skips the update and is counted).
    pub fn train_step(&mut self) -> Result<StepLog> {
        let started = Instant::now();
        let kernel_before = crate::model::decode_kernel::kernel_seconds();
        let mut rng = step_rng(self.opts.seed, self.step);
        // 1. The batch: scenes drawn with their input views and the rays to supervise.
        let samples = self.sample_batch(&mut rng)?;
        // 2. Forward: encode the input views, place the slots, decode the rays.
        let forward = self.forward(&samples, &mut rng)?;
        // 3. The loss: colour, latent penalty and the optional mask losses.
        let mut log = StepLog::default();
        let (loss, mse) = self.loss(&samples, &forward, &mut log)?;
        // 4. What the step measured, on the host.
        let loss_value = loss.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        let mse_value = mse.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        log.step = self.step;
        log.loss = loss_value;
        log.mse = mse_value;
        log.psnr = crate::metrics::psnr_from_mse(mse_value.max(1e-12));
        log.lr = self.learning_rate();
        let rgb_host = forward.decoded.rgb.flatten_all()?.to_vec1::<f32>()?;
        let s = 1 + self.scene_slots();
        ray_metrics(
            &mut log,
            &samples,
            &rgb_host,
            &forward.targets,
            &forward.weights_host,
            s,
        );
        log.forward_s = started.elapsed().as_secs_f64();
        // 5. Backward and Adam, unless the loss or a gradient is not finite.
        self.update(&loss, loss_value.is_finite(), &mut log)?;
        self.step += 1;
        log.seconds = started.elapsed().as_secs_f64();
        log.decoder_s = crate::model::decode_kernel::kernel_seconds() - kernel_before;
        log.rays_per_s = forward.targets.len() as f64 / 3.0 / log.seconds;
        Ok(log)
    }

    /// Views each scene encodes: its context views, or one.
    fn inputs_per_scene(&self) -> usize {
        self.opts.context_views.len().max(1)
    }

    /// Foreground slots of a scene: `num_slots` from each of its input views.
    fn scene_slots(&self) -> usize {
        self.num_slots * self.inputs_per_scene()
    }

    /// Step 1: `batch_scenes` scenes drawn with `rng`, each with its input views and rays.
    fn sample_batch(&self, rng: &mut StdRng) -> Result<Vec<SceneSample>> {
        let opts = &self.opts;
        let sampling = RaySampling {
            views: opts.views_per_scene,
            context_views: opts.context_views.clone(),
            rays_per_view: opts.rays_per_view,
            object_fraction: opts.object_fraction,
            mask_margin: opts.mask_margin,
            mask_claim: opts.mask_claim,
            shadow_depth: opts.mask_shadow_depth,
        };
        (0..opts.batch_scenes)
            .map(|_| {
                let i = rng.random_range(0..self.data.len());
                sample_scene(&self.data[i], &sampling, rng)
            })
            .collect()
    }

    /// Step 2: the input views encoded (slot noise from `rng`), the slots placed in their
    /// frames (each view's from its camera; a scene's slots are those of all its input views),
    /// and the sampled rays decoded.
    fn forward(&self, samples: &[SceneSample], rng: &mut StdRng) -> Result<Forward> {
        let model = self.colf.model();
        let cfg = self.colf.config();
        let dev = self.colf.device();
        let inputs: Vec<&InputView> = samples.iter().flat_map(|s| &s.inputs).collect();
        let images = inputs
            .iter()
            .map(|v| image_tensor(cfg, &v.image, v.h, v.w, dev))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let mut encoded = model.encode(&Tensor::cat(&images, 0)?, self.num_slots, rng)?;
        if cfg.frames_from_residual {
            // The input views' object proposals (against the known background) place the slots.
            let objects = inputs
                .iter()
                .map(|v| {
                    let Some(ids) = &v.mask else {
                        bail!("`frames_from_residual` places slots from the input view's object proposals: train with --proposals");
                    };
                    Ok((crate::proposals::object_pixels(ids), v.h, v.w))
                })
                .collect::<Result<Vec<_>>>()?;
            let objects: Vec<(&[f32], usize, usize)> =
                objects.iter().map(|(p, h, w)| (&p[..], *h, *w)).collect();
            encoded.attend_within_pixels(&objects, crate::model::frames::MIN_OBJECT_SHARE)?;
        }
        let centroids = encoded.fg_centroid.to_vec3::<f32>()?;
        let bottoms = encoded.fg_bottom.to_vec2::<f32>()?;
        let view_frames: Vec<Vec<DMat4>> = inputs
            .iter()
            .zip(centroids.iter().zip(&bottoms))
            .map(|(v, (c, bottom))| {
                let c: Vec<[f32; 2]> = c.iter().map(|p| [p[0], p[1]]).collect();
                crate::model::frames::slot_frames(cfg, &v.frame, &c, bottom)
            })
            .collect();
        let c = self.inputs_per_scene();
        let frames: Vec<Vec<DMat4>> = view_frames.chunks(c).map(|f| f.concat()).collect();
        let fields = if c == 1 {
            model.prepare(&encoded.fg, &encoded.bg)?
        } else {
            // Scene-major images: a scene's C·K slots are its views' slots in order, and its
            // background latent the mean of its views' (one background a scene).
            let (n, k, d) = encoded.fg.dims3()?;
            let fg = encoded.fg.reshape((n / c, c * k, d))?;
            let bg = encoded.bg.reshape((n / c, c, d))?.mean(1)?;
            model.prepare(&fg, &bg)?
        };
        let scene_rays: Vec<SceneRays> = samples
            .iter()
            .zip(&frames)
            .map(|(s, f)| SceneRays {
                slot_to_world: f,
                origins: &s.origins,
                dirs: &s.dirs,
            })
            .collect();
        let rays = RayBatch::new(cfg, &scene_rays, dev)?;
        let decoded = model.decode(&fields, &rays)?;
        let targets: Vec<f32> = samples
            .iter()
            .flat_map(|s| s.targets.iter().copied())
            .collect();
        let weights_host = decoded.weights.flatten_all()?.to_vec1::<f32>()?;
        Ok(Forward {
            encoded,
            decoded,
            targets,
            weights_host,
        })
    }

    /// Step 3: the loss and the colour MSE (for the log); the mask losses' values go to `log`.
    fn loss(
        &self,
        samples: &[SceneSample],
        forward: &Forward,
        log: &mut StepLog,
    ) -> Result<(Tensor, Tensor)> {
        let opts = &self.opts;
        let (b, k) = (samples.len(), self.scene_slots());
        let r = samples[0].origins.len();
        let Forward {
            encoded,
            decoded,
            targets,
            weights_host,
        } = forward;
        let target = Tensor::from_vec(targets.clone(), (b, r, 3), self.colf.device())?;
        let diff = (&decoded.rgb - &target)?;
        let mse = diff.sqr()?.mean_all()?;
        let mut loss = mse.clone();
        if opts.l1_weight > 0.0 {
            loss = (loss + (diff.abs()?.mean_all()? * opts.l1_weight)?)?;
        }
        if opts.latent_weight > 0.0 && k > 0 {
            loss = (loss + (encoded.fg.sqr()?.mean_all()? * opts.latent_weight)?)?;
        }
        let s = 1 + k;
        if opts.mask_weight > 0.0 && samples.iter().all(|s| s.has_masks) {
            let (mut index, mut valid) = matched_targets(samples, weights_host, s);
            let cfg = self.colf.config();
            if cfg.cull_behind > 0.0 || cfg.slot_reach > 0.0 {
                let log_weights = decoded.log_weights.flatten_all()?.to_vec1::<f32>()?;
                leave_out_culled(&mut index, &mut valid, &log_weights, s);
            }
            let ray_weights = balanced_ray_weights(&index, &valid);
            let ce = weighted_cross_entropy(&decoded.log_weights, index, ray_weights)?;
            log.mask_loss = Some(ce.to_scalar::<f32>()? as f64);
            loss = (loss + (ce * opts.mask_weight)?)?;
        }
        if opts.attention_mask_weight > 0.0 && k > 0 {
            if let Some(ce) = self.attention_mask_loss(samples, encoded)? {
                log.attention_mask_loss = Some(ce.to_scalar::<f32>()? as f64);
                loss = (loss + (ce * opts.attention_mask_weight)?)?;
            }
        }
        Ok((loss, mse))
    }

    /// Supervises slot attention itself: each token's attention over the slots against the
    /// input view's mask, objects matched to slots on the attention. None without masks.
    fn attention_mask_loss(
        &self,
        samples: &[SceneSample],
        encoded: &SlotOutput,
    ) -> Result<Option<Tensor>> {
        let inputs: Vec<&InputView> = samples.iter().flat_map(|s| &s.inputs).collect();
        let Some(masks) = inputs
            .iter()
            .map(|v| v.mask.as_ref())
            .collect::<Option<Vec<_>>>()
        else {
            return Ok(None);
        };
        let g = self.colf.config().token_grid();
        let s = 1 + self.num_slots;
        let attention = encoded
            .log_attention
            .exp()?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let (mut index, mut valid) = (Vec::new(), Vec::new());
        // One encoded image at a time: each view's attention over its own slots.
        for (i, (view, mask)) in inputs.iter().zip(masks).enumerate() {
            let exclusion = MaskExclusion {
                mask,
                image: &view.image,
                w: view.w,
                h: view.h,
                margin: self.opts.mask_margin,
                shadow_below: view.shadow_below,
            };
            let (ids, near) = token_ids(&exclusion, g);
            let image = &attention[i * g * g * s..(i + 1) * g * g * s];
            let (i, v) = match_objects(&ids, image, s, Some(&near));
            index.extend(i);
            valid.extend(v);
        }
        let weights = balanced_ray_weights(&index, &valid);
        Ok(Some(weighted_cross_entropy(
            &encoded.log_attention,
            index,
            weights,
        )?))
    }

    /// Step 5: backward and one Adam step when `finite`; otherwise (or when a gradient is not
    /// finite) the step is skipped and counted, and too many skipped steps end the run.
    fn update(&mut self, loss: &Tensor, finite: bool, log: &mut StepLog) -> Result<()> {
        let lr = self.learning_rate();
        let update = if finite {
            let backward_started = Instant::now();
            let grads = loss.backward()?;
            log.backward_s = backward_started.elapsed().as_secs_f64();
            let update_started = Instant::now();
            // Non-finite gradients: skipped like a non-finite loss.
            let stats = self.adam.step(&grads, lr).ok();
            log.update_s = update_started.elapsed().as_secs_f64();
            stats
        } else {
            None
        };
        match update {
            Some(stats) => log.grad_norm = stats.grad_norm,
            None => {
                self.bad_steps += 1;
                log.skipped = true;
                if self.bad_steps > self.opts.max_bad_steps {
                    bail!(
                        "{} steps had a non-finite loss or gradient (limit {}); lower the learning rate or check the data",
                        self.bad_steps,
                        self.opts.max_bad_steps
                    );
                }
            }
        }
        Ok(())
    }

    /// Saves the model file and the checkpoint (both atomically; the checkpoint holds the model,
    /// the optimizer moments and the step, in one file, so they can never disagree).
    pub fn save(&self) -> Result<()> {
        let (model_bytes, host) = self.model_file()?;
        self.write_model_and_checkpoint(&model_bytes, &host)
    }

    /// `save` with the model file already made (`model_file`), so a step that is also kept
    /// serialises the weights once.
    fn write_model_and_checkpoint(&self, model_bytes: &[u8], host: &HostParams) -> Result<()> {
        crate::io::write_atomic(&self.opts.out, model_bytes)?;
        let adam = self.adam.state_tensors("adam/")?;
        let mut tensors: Vec<F32Tensor> = host
            .iter()
            .map(|(name, (shape, data))| F32Tensor {
                name: name.as_str(),
                shape: shape.clone(),
                data,
            })
            .collect();
        let prefixed: Vec<String> = host.keys().map(|n| format!("model/{n}")).collect();
        for (t, name) in tensors.iter_mut().zip(&prefixed) {
            t.name = name.as_str();
        }
        tensors.extend(adam.iter().map(|(n, s, d)| F32Tensor {
            name: n,
            shape: s.clone(),
            data: d,
        }));
        let mut meta = BTreeMap::new();
        meta.insert("format".into(), CHECKPOINT_FORMAT.to_string());
        meta.insert("config".into(), self.colf.config().to_json());
        meta.insert("step".into(), self.step.to_string());
        meta.insert("bad_steps".into(), self.bad_steps.to_string());
        meta.insert("options".into(), serde_json::to_string(&self.opts)?);
        meta.insert(
            history::METADATA_KEY.into(),
            history::to_json(&self.training_records()),
        );
        crate::io::write_in_folder(
            &self.opts.checkpoint_path(),
            &serialize_f32(&tensors, &meta),
        )
    }

    /// The current weights as a model file's bytes, and as host tensors.
    fn model_file(&self) -> Result<(Vec<u8>, HostParams)> {
        let host = checkpoint::to_host(self.colf.parameters())?;
        let (model_bytes, _) = checkpoint::to_bytes(
            self.colf.config(),
            &host,
            &self.training_records(),
            &Default::default(),
        );
        Ok((model_bytes, host))
    }

    /// Evaluates on the evaluation set (if any) with the current weights.
    pub fn evaluate(&self) -> Result<Option<crate::evaluate::DatasetScores>> {
        let Some(data) = &self.eval_data else {
            return Ok(None);
        };
        let (scores, _) = crate::evaluate::evaluate(
            &self.colf,
            data,
            Some(self.opts.eval_scenes),
            &crate::evaluate::Protocol {
                inputs: match &self.opts.context_views[..] {
                    [] => vec![0],
                    views => views.to_vec(),
                },
                novel: None,
            },
            &crate::encode::EncodeOptions::one_pass(self.num_slots),
            Vec::new(),
            |_, _, _| Ok(()),
        )?;
        Ok(Some(scores))
    }

    /// Trains until `opts.steps` or until `stop` is set; checkpoints every
    /// `checkpoint_every` steps and at the end; `on_log` sees every step (and evaluations).
    pub fn run(
        &mut self,
        stop: &AtomicBool,
        mut on_log: impl FnMut(&serde_json::Value),
    ) -> Result<()> {
        while self.step < self.opts.steps && !stop.load(Ordering::Relaxed) {
            let log = self.train_step()?;
            on_log(&serde_json::to_value(&log)?);
            let every = |n: u64| n > 0 && self.step.is_multiple_of(n);
            if every(self.opts.eval_every) {
                if let Some(scores) = self.evaluate()? {
                    on_log(&serde_json::json!({"step": self.step, "eval": scores}));
                }
            }
            let (checkpoint, keep) = (
                every(self.opts.checkpoint_every),
                every(self.opts.keep_every),
            );
            if checkpoint || keep {
                let (model_bytes, host) = self.model_file()?;
                if checkpoint {
                    self.write_model_and_checkpoint(&model_bytes, &host)?;
                }
                if keep {
                    crate::io::write_in_folder(&self.opts.snapshot_path(self.step), &model_bytes)?;
                }
            }
        }
        self.save()
    }
}

/// With `--resume`: the step of OUT's checkpoint when it has already reached `opts.steps` and
/// OUT is there, so the run is done; read from the checkpoint's header before any data, which
/// a finished run does not need (loading a large set and its proposals takes minutes).
pub fn finished_step(opts: &TrainOptions) -> Result<Option<u64>> {
    let path = opts.checkpoint_path();
    if !path.is_file() || !opts.out.is_file() {
        return Ok(None);
    }
    let meta = crate::tensorfile::read_header_metadata(&path)?;
    let step = checkpoint_number(&meta, &path.display().to_string(), "step")?;
    Ok((step >= opts.steps).then_some(step))
}

/// Metadata value `key` of a training checkpoint's header `meta` (file `name`) as a number,
/// after checking that the file is a colf training checkpoint.
fn checkpoint_number(meta: &BTreeMap<String, String>, name: &str, key: &str) -> Result<u64> {
    let entry = |k: &str| {
        meta.get(k)
            .ok_or_else(|| anyhow!("{name}: metadata key `{k}` is missing"))
    };
    if entry("format")? != CHECKPOINT_FORMAT {
        bail!("{name}: not a colf training checkpoint");
    }
    entry(key)?
        .parse()
        .map_err(|_| anyhow!("{name}: metadata `{key}` is not a number"))
}

/// A training checkpoint as read back.
struct SavedRun {
    colf: Colf,
    step: u64,
    bad_steps: u64,
    /// The initial model (`--init`) named by the options the run stored.
    init_path: Option<PathBuf>,
}

/// Reads a training checkpoint: the model (with its training records), the step, the count of
/// bad steps and the run's initial model.
fn load_checkpoint(bytes: &[u8], name: &str) -> Result<SavedRun> {
    let file = TensorFile::parse(bytes, name)?;
    let step = checkpoint_number(&file.metadata, name, "step")?;
    let bad = checkpoint_number(&file.metadata, name, "bad_steps")?;
    let config = Config::from_json(file.require_metadata("config")?)
        .with_context(|| format!("{name}: config"))?;
    let mut host: HostParams = BTreeMap::new();
    for tensor in file.tensors.names() {
        if let Some(param) = tensor.strip_prefix("model/") {
            let shape = file.tensors.tensor(tensor)?.shape().to_vec();
            let expected: Vec<Option<usize>> = shape.iter().map(|&d| Some(d)).collect();
            host.insert(param.to_string(), file.f32_tensor(tensor, &expected)?);
        }
    }
    let training = history::from_metadata(&file.metadata, name)?;
    let (model_bytes, _) = checkpoint::to_bytes(&config, &host, &training, &Default::default());
    let init_path = file
        .metadata
        .get("options")
        .and_then(|o| serde_json::from_str::<serde_json::Value>(o).ok())
        .and_then(|o| Some(PathBuf::from(o.get("init")?.as_str()?)));
    Ok(SavedRun {
        colf: Colf::from_bytes(&model_bytes, name)?,
        step,
        bad_steps: bad,
        init_path,
    })
}

/// This run's training record (its `steps` are filled in as it goes): the data, whether masks
/// were there and whether anything used them, the schedule and the loss weights.
fn run_record(opts: &TrainOptions, data: &[SceneData], init: Option<String>) -> TrainingRun {
    let mask_supervision =
        opts.mask_weight > 0.0 || opts.attention_mask_weight > 0.0 || opts.object_fraction > 0.0;
    let losses = [
        ("l2", 1.0),
        ("l1", opts.l1_weight),
        ("latent", opts.latent_weight),
        ("mask", opts.mask_weight),
        ("attention_mask", opts.attention_mask_weight),
    ]
    .into_iter()
    .filter(|&(_, w)| w != 0.0)
    .map(|(k, w)| (k.to_string(), w))
    .collect();
    TrainingRun {
        data: opts.data.display().to_string(),
        engine: dataset_engine(&opts.data),
        scenes: data.len(),
        masks_in_data: !opts.proposals
            && data
                .iter()
                .any(|s| s.views.iter().any(|v| v.mask.is_some())),
        masks_used: mask_supervision && !opts.proposals,
        proposals: mask_supervision && opts.proposals,
        preset: init.is_none().then(|| opts.preset.clone()),
        init,
        config_overrides: opts.config_overrides.clone(),
        slot_values: (opts.init.is_some()
            && opts.slot_values != SlotValues::Copies
            && opts.config_overrides.iter().any(|s| {
                // Keys as `Config::with_overrides` reads them.
                s.split_once('=')
                    .is_some_and(|(key, _)| key.trim() == "slot_dim")
            }))
        .then_some(opts.slot_values),
        frozen: opts.freeze.clone(),
        lr_scale: opts.lr_scale.clone(),
        steps: 0,
        planned_steps: opts.steps,
        batch: opts.batch_scenes,
        views: opts.views_per_scene,
        context_views: opts.context_views.clone(),
        rays: opts.rays_per_view,
        lr: opts.lr,
        warmup: opts.warmup,
        decay_from: opts.decay_from,
        final_lr: opts.decay_from.map(|_| opts.final_lr),
        losses,
        object_fraction: opts.object_fraction,
        mask_margin: opts.mask_margin,
        mask_claim: opts.mask_claim,
        mask_shadow_depth: opts.mask_shadow_depth,
        seed: opts.seed,
    }
}

/// The renderer named by a colf-synth folder's `dataset.json` (`analytic` when it names none);
/// `None` for other folders.
fn dataset_engine(root: &Path) -> Option<String> {
    let text = std::fs::read_to_string(root.join("dataset.json")).ok()?;
    let json: serde_json::Value = serde_json::from_str(&text).ok()?;
    if json.get("format")?.as_str()? != "colf-synth/1" {
        return None;
    }
    Some(
        json.get("engine")
            .and_then(|e| e.as_str())
            .unwrap_or("analytic")
            .to_string(),
    )
}

/// Mask supervision targets: per scene, objects are matched to foreground slots by the
/// Hungarian method on the summed compositor weights (the matching the model is closest to),
/// background rays target the background. Returns per ray the target field index and a 0/1
/// validity (objects left unmatched when there are more objects than slots are ignored).
fn matched_targets(samples: &[SceneSample], weights: &[f32], s: usize) -> (Vec<u32>, Vec<f32>) {
    let r = samples[0].ids.len();
    let mut index = Vec::with_capacity(samples.len() * r);
    let mut valid = Vec::with_capacity(samples.len() * r);
    for (bi, sample) in samples.iter().enumerate() {
        // Scene-wide ids are matched over all the scene's rays; view-local ones view by view.
        let block = sample.view_block.unwrap_or(r);
        let scene = &weights[bi * r * s..(bi + 1) * r * s];
        let (i, v) = match_in_blocks(&sample.ids, &sample.near_object, scene, s, block);
        index.extend(i);
        valid.extend(v);
    }
    (index, valid)
}

/// The compositor's mask loss of one batch of rays against object proposals, as training's
/// (`--mask-weight`), for test-time refinement: `log_weights` [1, R, S] (`Decoded`), `ids` the
/// rays' proposal ids and `groups` the rays' views (ids are local to a view, so objects are
/// matched to slots view by view). Rays whose matched slot is culled or out of reach there
/// are left out; background and object rays carry half of the loss each.
pub(crate) fn proposal_mask_loss(
    log_weights: &Tensor,
    ids: &[u8],
    groups: &[usize],
) -> Result<Tensor> {
    let (_, r, s) = log_weights.dims3()?;
    if ids.len() != r || groups.len() != r {
        bail!(
            "mask loss: {} ids and {} groups for {r} rays",
            ids.len(),
            groups.len()
        );
    }
    let log_host = log_weights.flatten_all()?.to_vec1::<f32>()?;
    let weights: Vec<f32> = log_host.iter().map(|l| l.exp()).collect();
    let (mut index, mut valid) = (vec![0u32; r], vec![0f32; r]);
    let mut names: Vec<usize> = groups.to_vec();
    names.sort_unstable();
    names.dedup();
    for group in names {
        let members: Vec<usize> = (0..r).filter(|&e| groups[e] == group).collect();
        let group_ids: Vec<u8> = members.iter().map(|&e| ids[e]).collect();
        let group_weights: Vec<f32> = members
            .iter()
            .flat_map(|&e| weights[e * s..(e + 1) * s].iter().copied())
            .collect();
        let (i, v) = match_objects(&group_ids, &group_weights, s, None);
        for ((&e, i), v) in members.iter().zip(i).zip(v) {
            index[e] = i;
            valid[e] = v;
        }
    }
    leave_out_culled(&mut index, &mut valid, &log_host, s);
    let ray_weights = balanced_ray_weights(&index, &valid);
    Ok(weighted_cross_entropy(log_weights, index, ray_weights)?)
}

/// [`proposal_mask_loss`] without the matching: an object ray asks only that *some*
/// foreground slot draw it (−log Σₖ wₖ over the slots), a background ray that the background
/// does (−log w₀), each kind carrying half of the loss; which slot draws which object is left
/// to the colour loss. Rays that are neither (unsure), and object rays no slot can reach
/// (culled or beyond reach), are left out. None when no ray is left.
pub(crate) fn proposal_foreground_loss(log_weights: &Tensor, ids: &[u8]) -> Result<Option<Tensor>> {
    let (_, r, s) = log_weights.dims3()?;
    if ids.len() != r {
        bail!("mask loss: {} ids for {r} rays", ids.len());
    }
    let log_host = log_weights.flatten_all()?.to_vec1::<f32>()?;
    let reachable = |e: usize| {
        log_host[e * s + 1..(e + 1) * s]
            .iter()
            .any(|&l| l > CULLED_LOG_WEIGHT)
    };
    let objects: Vec<u32> = (0..r)
        .filter(|&e| is_instance(ids[e]) && reachable(e))
        .map(|e| e as u32)
        .collect();
    let background: Vec<u32> = (0..r).filter(|&e| ids[e] == 0).map(|e| e as u32).collect();
    let dev = log_weights.device();
    let mean_log = |rays: &[u32], foreground: bool| -> Result<Option<Tensor>> {
        if rays.is_empty() || (foreground && s < 2) {
            return Ok(None);
        }
        let index = Tensor::from_vec(rays.to_vec(), rays.len(), dev)?;
        let picked = log_weights.index_select(&index, 1)?;
        let log_p = if foreground {
            picked.narrow(2, 1, s - 1)?.log_sum_exp(2)?
        } else {
            picked.narrow(2, 0, 1)?.squeeze(2)?
        };
        Ok(Some(log_p.mean_all()?.neg()?))
    };
    Ok(
        match (mean_log(&objects, true)?, mean_log(&background, false)?) {
            (Some(o), Some(b)) => Some(((o + b)? * 0.5)?),
            (one, other) => one.or(other),
        },
    )
}

/// Below this log weight a (ray, slot) pair was culled (`Config::cull_behind` pushes the slot
/// 10⁶ units back: log weights near −10⁵) or the slot is absent (beyond `Config::slot_reach`:
/// −∞); no score gap of a drawn slot comes near it.
const CULLED_LOG_WEIGHT: f32 = -1e4;

/// Leaves out of the compositor's mask loss the rays whose matched slot (`index`, per ray) is
/// culled or absent there (`log_weights` [rays, s]): the slot lies behind that ray's camera, or
/// beyond its reach, and cannot be asked to draw it; its log weight would make the loss ~10⁵
/// (docs/training-log.md, c1k) or infinite. Such a ray's target becomes the background, whose
/// log weight is finite, so that its weight of 0 leaves no NaN.
fn leave_out_culled(index: &mut [u32], valid: &mut [f32], log_weights: &[f32], s: usize) {
    for (ray, (target, v)) in index.iter_mut().zip(valid.iter_mut()).enumerate() {
        if log_weights[ray * s + *target as usize] < CULLED_LOG_WEIGHT {
            *v = 0.0;
            *target = 0;
        }
    }
}

/// [`match_objects`] on each run of `block` consecutive elements separately (one view's rays,
/// when ids are local to each view), ignoring the elements `near` marks.
fn match_in_blocks(
    ids: &[u8],
    near: &[bool],
    weights: &[f32],
    s: usize,
    block: usize,
) -> (Vec<u32>, Vec<f32>) {
    let block = block.max(1);
    let (mut index, mut valid) = (Vec::with_capacity(ids.len()), Vec::with_capacity(ids.len()));
    for start in (0..ids.len()).step_by(block) {
        let end = (start + block).min(ids.len());
        let (i, v) = match_objects(
            &ids[start..end],
            &weights[start * s..end * s],
            s,
            Some(&near[start..end]),
        );
        index.extend(i);
        valid.extend(v);
    }
    (index, valid)
}

/// One scene's matching: `ids` per element (ray or token; 0 = background), `weights` the
/// model's soft assignment of each element to the s fields (background first), row-major.
/// Objects are matched to foreground fields by the Hungarian method on their summed weights;
/// returns per element the target field and a 0/1 validity (objects beyond the slot count,
/// the smallest ones, are left out, and so are the elements `ignored` marks).
fn match_objects(
    ids: &[u8],
    weights: &[f32],
    s: usize,
    ignored: Option<&[bool]>,
) -> (Vec<u32>, Vec<f32>) {
    use pathfinding::prelude::{kuhn_munkres, Matrix};
    let mut objects: Vec<u8> = ids.iter().copied().filter(|&id| is_instance(id)).collect();
    objects.sort_unstable();
    objects.dedup();
    let k = s - 1;
    let rows = objects.len().min(k);
    let mut assignment = BTreeMap::new();
    if rows > 0 {
        // Keep the objects with the most elements when there are more objects than slots.
        objects.sort_by_key(|&o| std::cmp::Reverse(ids.iter().filter(|&&i| i == o).count()));
        objects.truncate(rows);
        let mut overlap = vec![0i64; rows * k];
        for (e, &id) in ids.iter().enumerate() {
            if let Some(row) = objects.iter().position(|&o| o == id) {
                let w = &weights[e * s..(e + 1) * s];
                for slot in 0..k {
                    overlap[row * k + slot] += (w[1 + slot] * 1e4) as i64;
                }
            }
        }
        let matrix = Matrix::from_vec(rows, k, overlap).expect("rows × k");
        let (_, cols) = kuhn_munkres(&matrix);
        for (row, col) in cols.into_iter().enumerate() {
            assignment.insert(objects[row], col as u32 + 1);
        }
    }
    ids.iter()
        .enumerate()
        .map(|(e, &id)| match (id, assignment.get(&id)) {
            _ if ignored.is_some_and(|ignored| ignored[e]) => (0, 0.0),
            (0, _) => (0, 1.0),
            (_, Some(&field)) => (field, 1.0),
            (_, None) => (0, 0.0),
        })
        .unzip()
}

/// Object ids of a token grid (g×g, row-major) from a view's mask: each token takes the id of
/// the pixel under its centre; and whether the mask losses leave that pixel to the colour loss.
fn token_ids(exclusion: &MaskExclusion, g: usize) -> (Vec<u8>, Vec<bool>) {
    let (w, h) = (exclusion.w, exclusion.h);
    (0..g * g)
        .map(|t| {
            let (tx, ty) = (t % g, t / g);
            let x = ((((tx as f64 + 0.5) / g as f64) * w as f64) as usize).min(w - 1);
            let y = ((((ty as f64 + 0.5) / g as f64) * h as f64) as usize).min(h - 1);
            (exclusion.mask[y * w + x], exclusion.leaves(x, y))
        })
        .unzip()
}

/// Cross-entropy of labels `index` under log-probabilities `log_p` [B, N, S], each element
/// weighted by `weights` (summing to 1): −Σ w · log p[index].
fn weighted_cross_entropy(
    log_p: &Tensor,
    index: Vec<u32>,
    weights: Vec<f32>,
) -> candle_core::Result<Tensor> {
    let (b, n, _) = log_p.dims3()?;
    let dev = log_p.device();
    let index = Tensor::from_vec(index, (b, n, 1), dev)?;
    let weights = Tensor::from_vec(weights, (b, n), dev)?;
    let picked = log_p.gather(&index, D::Minus1)?.squeeze(D::Minus1)?;
    (picked * weights)?.sum_all()?.neg()
}

/// Per-ray weights of the mask cross-entropy: background rays and object rays each carry half
/// of the loss (objects cover ~6 % of a clevr567 view, so a plain mean is won by giving every
/// ray to the background); invalid rays weigh 0. The weights sum to 1.
fn balanced_ray_weights(index: &[u32], valid: &[f32]) -> Vec<f32> {
    let is_object = |i: usize| valid[i] > 0.0 && index[i] > 0;
    let is_background = |i: usize| valid[i] > 0.0 && index[i] == 0;
    let objects = (0..index.len()).filter(|&i| is_object(i)).count();
    let background = (0..index.len()).filter(|&i| is_background(i)).count();
    let (obj_total, bg_total) = match (objects, background) {
        (0, _) => (0.0, 1.0),
        (_, 0) => (1.0, 0.0),
        _ => (0.5, 0.5),
    };
    (0..index.len())
        .map(|i| {
            if is_object(i) {
                obj_total / objects as f32
            } else if is_background(i) {
                bg_total / background as f32
            } else {
                0.0
            }
        })
        .collect()
}

/// Fills the object-aware metrics of `log` from the sampled rays.
fn ray_metrics(
    log: &mut StepLog,
    samples: &[SceneSample],
    rgb: &[f32],
    targets: &[f32],
    weights: &[f32],
    s: usize,
) {
    let r = samples[0].ids.len();
    let (mut obj_sq, mut obj_n, mut fg_sum) = (0.0f64, 0usize, 0.0f64);
    let (mut aris, mut used) = (Vec::new(), 0usize);
    for (bi, sample) in samples.iter().enumerate() {
        // FG-ARI per group of rays whose ids share a meaning: the scene for scene-wide ids,
        // each view for view-local ones (proposals).
        let block = sample.view_block.unwrap_or(r).max(1);
        let mut groups: Vec<(Vec<u32>, Vec<u32>)> = vec![Default::default(); r.div_ceil(block)];
        let mut won = vec![false; s];
        for (ri, &id) in sample.ids.iter().enumerate() {
            let at = bi * r + ri;
            let w = &weights[at * s..(at + 1) * s];
            let label = (0..s).fold(0, |best, i| if w[i] > w[best] { i } else { best });
            won[label] = true;
            if is_instance(id) {
                for c in 0..3 {
                    let e = (rgb[3 * at + c] - targets[3 * at + c]) as f64;
                    obj_sq += e * e;
                }
                obj_n += 3;
                fg_sum += 1.0 - w[0] as f64;
                let (pred, gt) = &mut groups[ri / block];
                pred.push(label as u32);
                gt.push(id as u32);
            }
        }
        used += won[1..].iter().filter(|&&x| x).count();
        for (pred, gt) in groups.iter().filter(|(_, gt)| !gt.is_empty()) {
            if let Ok(a) = crate::metrics::ari(pred, gt) {
                aris.push(a);
            }
        }
    }
    if obj_n > 0 {
        log.obj_psnr = Some(crate::metrics::psnr_from_mse(
            (obj_sq / obj_n as f64).max(1e-12),
        ));
        log.fg_share = Some(fg_sum / (obj_n / 3) as f64);
    }
    if !aris.is_empty() {
        log.fg_ari = Some(aris.iter().sum::<f64>() / aris.len() as f64);
    }
    log.slots_used = used as f64 / samples.len() as f64;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn snapshots_are_named_by_their_step() {
        let opts = |out: &str| TrainOptions {
            out: out.into(),
            ..TrainOptions::default()
        };
        assert_eq!(
            opts("runs/m.safetensors").snapshot_path(2000),
            PathBuf::from("runs/m.step2000.safetensors")
        );
        assert_eq!(
            opts("runs/model").snapshot_path(7),
            PathBuf::from("runs/model.step7")
        );
    }

    #[test]
    fn learning_rate_warms_up_then_decays_by_a_half_cosine() {
        let mut opts = TrainOptions {
            lr: 1e-3,
            warmup: 10,
            steps: 100,
            ..TrainOptions::default()
        };
        assert!((learning_rate(&opts, 4) - 5e-4).abs() < 1e-12);
        assert_eq!(learning_rate(&opts, 99), 1e-3);
        opts.decay_from = Some(50);
        opts.final_lr = 1e-4;
        assert_eq!(learning_rate(&opts, 49), 1e-3);
        assert_eq!(learning_rate(&opts, 50), 1e-3);
        assert!((learning_rate(&opts, 75) - 5.5e-4).abs() < 1e-12);
        assert!((learning_rate(&opts, 100) - 1e-4).abs() < 1e-12);
        // Steps past the end (a resumed run's `steps` lowered) stay at the final rate.
        assert!((learning_rate(&opts, 500) - 1e-4).abs() < 1e-12);
    }

    #[test]
    fn objects_match_the_slots_that_hold_them() {
        // 3 fields (background + 2 slots); object 5 sits in slot 2, object 9 in slot 1.
        let ids = [0u8, 5, 5, 9, 0];
        let weights = [
            0.9, 0.05, 0.05, // background element
            0.1, 0.2, 0.7, // object 5
            0.1, 0.1, 0.8, // object 5
            0.2, 0.7, 0.1, // object 9
            0.8, 0.1, 0.1, // background element
        ];
        let (index, valid) = match_objects(&ids, &weights, 3, None);
        assert_eq!(index, vec![0, 2, 2, 1, 0]);
        assert_eq!(valid, vec![1.0; 5]);
        // Ignored elements (a background pixel next to an object) weigh nothing.
        let ignored = [true, false, false, false, false];
        let (index, valid) = match_objects(&ids, &weights, 3, Some(&ignored));
        assert_eq!(index, vec![0, 2, 2, 1, 0]);
        assert_eq!(valid, vec![0.0, 1.0, 1.0, 1.0, 1.0]);
        // One slot for two objects: the bigger object (5) is kept, 9 is ignored.
        let (index, valid) = match_objects(&ids, &[0.5, 0.5].repeat(5), 2, None);
        assert_eq!(index, vec![0, 1, 1, 0, 0]);
        assert_eq!(valid, vec![1.0, 1.0, 1.0, 0.0, 1.0]);
    }

    #[test]
    fn token_ids_sample_the_mask_under_each_token_centre() {
        // 4×4 mask, object 3 in the bottom-right 2×2 block; 2×2 tokens.
        let mut mask = vec![0u8; 16];
        for (x, y) in [(2, 2), (3, 2), (2, 3), (3, 3)] {
            mask[y * 4 + x] = 3;
        }
        let image = vec![0.5f32; 48];
        let margin = |margin| MaskExclusion {
            mask: &mask,
            image: &image,
            w: 4,
            h: 4,
            margin,
            shadow_below: None,
        };
        assert_eq!(token_ids(&margin(0), 2).0, vec![0, 0, 0, 3]);
        // Token centres are pixels (1, 1), (3, 1), (1, 3) and (3, 3): the three background
        // ones touch the object diagonally or sideways, so with a 1-pixel margin they are near
        // it; with none, nothing is.
        assert_eq!(token_ids(&margin(1), 2).1, vec![true, true, true, false]);
        assert_eq!(token_ids(&margin(0), 2).1, vec![false; 4]);
    }

    #[test]
    fn view_local_ids_are_matched_view_by_view() {
        // Two views of two rays each; id 1 is an object in both, but the model gives view 0's
        // to slot 1 (field 1) and view 1's to slot 2 (field 2). Fields: background, 2 slots.
        let ids = [1u8, 0, 1, 0];
        let near = [false; 4];
        let weights = [
            0.1, 0.8, 0.1, /* */ 0.9, 0.05, 0.05, /* */ 0.1, 0.1, 0.8, /* */ 0.9,
            0.05, 0.05,
        ];
        let (by_view, valid) = match_in_blocks(&ids, &near, &weights, 3, 2);
        assert_eq!(by_view, vec![1, 0, 2, 0]);
        assert_eq!(valid, vec![1.0; 4]);
        // Scene-wide, one id is one object: both rays go to one slot.
        let (scene_wide, _) = match_in_blocks(&ids, &near, &weights, 3, 4);
        assert_eq!(scene_wide[0], scene_wide[2]);
        // Unsure proposals are never an object to match, and ignored elements weigh 0.
        let ids = [crate::proposals::UNSURE, 1, 0, 0];
        let near = [true, false, false, false];
        let (index, valid) = match_in_blocks(&ids, &near, &weights, 3, 2);
        assert_eq!((index[0], valid[0]), (0, 0.0));
        assert_eq!((index[1], valid[1]), (1, 1.0));
    }

    #[test]
    fn culled_targets_leave_the_mask_loss() {
        // 3 rays, 3 fields: ray 1's target (slot 2) is culled there, ray 2's culled slot is
        // not its target, ray 0 is already left out.
        let mut index = [1u32, 2, 0];
        let mut valid = [0.0f32, 1.0, 1.0];
        let log_weights = [
            -0.1, -2.0, -1e5, //
            -0.5, -1.0, -1e5, //
            -0.2, -1e5, -3.0,
        ];
        leave_out_culled(&mut index, &mut valid, &log_weights, 3);
        assert_eq!(valid, [0.0, 0.0, 1.0]);
        assert_eq!(index, [1, 0, 0]);
        // A drawn slot far behind the front one keeps its target.
        let mut valid = [1.0f32];
        leave_out_culled(&mut [1], &mut valid, &[-0.01, -90.0], 2);
        assert_eq!(valid, [1.0]);
    }

    /// A slot absent beyond its reach has log weight −∞ there: the ray leaves the loss, and
    /// the loss stays finite with a finite gradient.
    #[test]
    fn absent_targets_leave_the_mask_loss_without_nan() {
        let mut index = vec![2u32, 2];
        let mut valid = vec![1.0f32, 1.0];
        let log_weights = [-0.1f32, -2.5, f32::NEG_INFINITY, -0.3, -1.5, -2.0];
        leave_out_culled(&mut index, &mut valid, &log_weights, 3);
        assert_eq!((index.clone(), valid.clone()), (vec![0, 2], vec![0.0, 1.0]));
        let log_p =
            candle_core::Var::from_vec(log_weights.to_vec(), (1, 2, 3), &candle_core::Device::Cpu)
                .unwrap();
        let weights = balanced_ray_weights(&index, &valid);
        let ce = weighted_cross_entropy(log_p.as_tensor(), index, weights).unwrap();
        assert!((ce.to_scalar::<f32>().unwrap() - 2.0).abs() < 1e-6);
        let grads = ce.backward().unwrap();
        let g = grads.get(log_p.as_tensor()).unwrap().flatten_all().unwrap();
        assert!(g.to_vec1::<f32>().unwrap().iter().all(|v| v.is_finite()));
    }

    #[test]
    fn mask_loss_weights_split_evenly_between_background_and_objects() {
        // 6 background rays, 2 object rays, 1 unmatched object ray.
        let index = [0, 0, 0, 0, 0, 0, 2, 3, 1];
        let valid = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0];
        let w = balanced_ray_weights(&index, &valid);
        let bg: f32 = w[..6].iter().sum();
        let obj: f32 = w[6..8].iter().sum();
        assert!((bg - 0.5).abs() < 1e-6 && (obj - 0.5).abs() < 1e-6);
        assert_eq!(w[8], 0.0);
        // Background only: the background rays carry everything.
        let w = balanced_ray_weights(&[0, 0], &[1.0, 1.0]);
        assert_eq!(w, vec![0.5, 0.5]);
    }

    /// The unmatched mask loss of refinement: −½ mean log(Σ foreground weights) over the object
    /// rays that some slot reaches, −½ mean log(background weight) over the background rays;
    /// unsure rays and unreachable object rays left out; None when no ray is left.
    #[test]
    fn the_foreground_loss_asks_objects_of_any_slot_and_the_background_of_itself() {
        use crate::proposals::UNSURE;
        let dev = candle_core::Device::Cpu;
        // Rays × (background, slot 1, slot 2) weights.
        let weights: [[f32; 3]; 5] = [
            [0.2, 0.5, 0.3],   // object
            [0.6, 0.1, 0.3],   // object
            [0.9, 0.05, 0.05], // background
            [0.5, 0.25, 0.25], // unsure: left out
            [1.0, 0.0, 0.0],   // object no slot reaches (log weight −∞): left out
        ];
        let log: Vec<f32> = weights.iter().flatten().map(|w| w.ln()).collect();
        let log_weights = Tensor::from_vec(log, (1, 5, 3), &dev).unwrap();
        let ids = [1, 2, 0, UNSURE, 1];
        let loss = proposal_foreground_loss(&log_weights, &ids)
            .unwrap()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        let objects = -(0.8f32.ln() + 0.4f32.ln()) / 2.0;
        let background = -0.9f32.ln();
        let expected = 0.5 * objects + 0.5 * background;
        assert!((loss - expected).abs() < 1e-5, "{loss} vs {expected}");
        // Objects only, then nothing to ask.
        let only = proposal_foreground_loss(&log_weights.narrow(1, 0, 2).unwrap(), &ids[..2])
            .unwrap()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!((only - objects).abs() < 1e-5);
        let unsure = proposal_foreground_loss(&log_weights.narrow(1, 3, 1).unwrap(), &[UNSURE]);
        assert!(unsure.unwrap().is_none());
        assert!(proposal_foreground_loss(&log_weights, &ids[..2]).is_err());
    }
}
