//! `colf-train`: make and train COLF models.

use crate::model::grow::SlotValues;
use clap::{Args, Parser, Subcommand};

/// Make and train COLF models.
#[derive(Parser, Debug)]
#[command(
    name = "colf-train",
    version,
    about = "Make and train colf models",
    long_about = "Make and train colf models (safetensors files holding every weight, the \
model's config and its identity; see docs/model.md).\n\n\
`colf-train init` writes a freshly initialised model: every weight is drawn from a random \
generator seeded by --seed and the weight's name, so the same preset and seed give a \
byte-identical file. Presets: small (trains on a 2-core CPU: 64x64 encoder input, 32x32 \
tokens, slot dimension 64, about 3 M parameters) and paper (the sizes of the COLF supplement: \
128x128 encoder input, slot dimension 128, light fields with 2 hidden layers of 256 units).\n\n\
`colf-train --data DIR --out MODEL` trains: each step takes --batch scenes, encodes one random \
view of each (or the views --context-views names, together), and supervises --rays random rays in each of --views views (the input view and \
novel views) with an L2 loss (+ --l1-weight L1) and a small penalty on the foreground latents; \
Adam with a linear warm-up. Every step draws its randomness from (--seed, step), so a run \
resumed with --resume from OUT.ckpt takes exactly the steps an uninterrupted run would. The \
model file OUT and the checkpoint OUT.ckpt (model + optimizer moments + step, one file) are \
written atomically every --checkpoint-every steps, at the end, and on SIGINT/SIGTERM. OUT, the \
file you name, is written like a shell redirect (a symbolic link keeps pointing at the file it \
names, which is replaced); the files colf-train names beside it (OUT.ckpt, OUT.log.jsonl, the \
--keep-every snapshots) replace a link found at their path and never follow it. Every \
step appends a JSON line to OUT.log.jsonl: step, loss, mse, psnr, obj_psnr (rays on objects), \
fg_share (foreground weight on object rays), fg_ari, slots_used, lr, grad_norm, rays_per_s, \
and the step's seconds split as forward_s, backward_s, update_s, with decoder_s the decode \
kernel's share of them; \
evaluations on --eval-data add lines with an \"eval\" object. A step with a non-finite loss or \
gradient is skipped and counted; more than --max-bad-steps abort the run.",
    after_help = "Examples:\n  colf-train init --preset small --seed 0 -o init.safetensors\n  \
colf-train init --preset paper -o paper-init.safetensors\n  \
colf-train --data data/train --eval-data data/test --out model.safetensors --steps 20000\n  \
colf-train --data data/train --out model.safetensors --steps 40000 --resume"
)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct TrainArgs {
    #[command(subcommand)]
    pub command: Option<TrainCommand>,

    #[command(flatten)]
    pub run: RunArgs,
}

/// Options of a training run (`colf-train --data DIR --out MODEL ...`).
#[derive(Args, Debug, Clone)]
pub struct RunArgs {
    /// Training data: a colf-synth folder or a uORF-layout folder.
    #[arg(long, value_name = "DIR", required = true)]
    pub data: Option<std::path::PathBuf>,

    /// Model file to write (at every checkpoint and at the end). The checkpoint is OUT.ckpt,
    /// the JSON-lines log OUT.log.jsonl.
    #[arg(long, value_name = "MODEL", required = true)]
    pub out: Option<std::path::PathBuf>,

    /// Start from this model, a file or a bundled model's name (`default`, `supervised`, `blender`): a
    /// curriculum (e.g. clevr567, then harder scenes), or a model that already separates
    /// objects fine-tuned on your own scenes.
    #[arg(long, value_name = "MODEL", conflicts_with = "resume")]
    pub init: Option<String>,

    /// Continue the run saved in OUT.ckpt (model, optimizer moments and step) up to --steps. A
    /// run whose checkpoint has reached --steps is done: nothing is read or written.
    #[arg(long)]
    pub resume: bool,

    /// Size preset of a fresh model (without --init or --resume).
    #[arg(long, value_name = "PRESET", value_parser = ["small", "paper"], default_value = "small")]
    pub preset: String,

    /// Total optimisation steps.
    #[arg(long, default_value_t = 10_000, value_name = "N")]
    pub steps: u64,

    /// Scenes per batch.
    #[arg(long, default_value_t = 4, value_name = "B")]
    pub batch: usize,

    /// Views supervised per scene: the encoded input view and VIEWS-1 novel views.
    #[arg(long, default_value_t = 2, value_name = "V")]
    pub views: usize,

    /// Encode these views of every scene together (comma-separated indices, e.g. 0,1: the
    /// context views of a City-Block street, one in front of each row of cars): each view's
    /// --slots slots are placed from its own camera, and together they are the scene's slots
    /// (its background latent the mean of the views'). The context views are supervised first,
    /// then VIEWS minus their number of others. Default: one random view.
    #[arg(long, value_delimiter = ',', value_name = "V,V")]
    pub context_views: Vec<usize>,

    /// Random rays supervised per view.
    #[arg(long, default_value_t = 512, value_name = "R")]
    pub rays: usize,

    /// Foreground slots (default: the model's).
    #[arg(long, value_name = "K")]
    pub slots: Option<usize>,

    /// Adam learning rate.
    #[arg(long, default_value_t = 2e-4, value_name = "LR")]
    pub lr: f64,

    /// Linear learning-rate warm-up, in steps.
    #[arg(long, default_value_t = 500, value_name = "N")]
    pub warmup: u64,

    /// Cosine decay of the learning rate from --lr at step N down to --final-lr at --steps
    /// (without it the rate stays constant after the warm-up). A step, not a fraction, so that a
    /// run resumed with more --steps keeps the rates it already used.
    #[arg(long, value_name = "N")]
    pub decay_from: Option<u64>,

    /// Learning rate reached at --steps when --decay-from is given.
    #[arg(long, default_value_t = 3e-5, value_name = "LR")]
    pub final_lr: f64,

    /// Weight of an L1 colour loss added to the L2 loss.
    #[arg(long, default_value_t = 0.0, value_name = "W")]
    pub l1_weight: f64,

    /// Weight of the mean squared foreground latent (keeps slot codes small).
    #[arg(long, default_value_t = 1e-4, value_name = "W")]
    pub latent_weight: f64,

    /// Weak supervision: cross-entropy between compositor weights and ground-truth masks, objects
    /// matched to slots by the Hungarian method (0 = unsupervised, the default).
    #[arg(long, default_value_t = 0.0, value_name = "W")]
    pub mask_weight: f64,

    /// Weak supervision of slot attention: cross-entropy between each token's attention over
    /// the slots and the input view's ground-truth mask, objects matched to slots by the
    /// Hungarian method on the attention (0 = none, the default).
    #[arg(long, default_value_t = 0.0, value_name = "W")]
    pub attention_mask_weight: f64,

    /// Share of each view's rays drawn from ground-truth object pixels (uses masks; 0 = uniform).
    #[arg(long, default_value_t = 0.0, value_name = "F")]
    pub object_fraction: f64,

    /// Train without labels: mask files are never opened, and the mask losses
    /// (--mask-weight, --attention-mask-weight) and --object-fraction use object proposals
    /// computed from each training image instead: a smooth floor fitted to the view, the pixels
    /// it cannot explain grouped into instances, shadows and edges left out
    /// (docs/training.md; `colf-train propose` writes and scores them).
    #[arg(long)]
    pub proposals: bool,

    /// With scenes that share one background (the city's street): make the object proposals
    /// against MODEL's background — a model whose background does not depend on the image, such
    /// as a static background field trained alone — rendered at each view's camera: pixels that
    /// differ from that render in hue are objects, those that differ only in brightness (a
    /// blurred edge, a shadow) are left to the colour loss. Implies --proposals.
    #[arg(long, value_name = "MODEL")]
    pub proposals_against: Option<std::path::PathBuf>,

    /// Mask losses (--mask-weight, --attention-mask-weight) ignore background pixels within PX
    /// pixels of an object: masks call an object's shadow background, but only the object's slot
    /// can draw it when the background cannot depend on the image (--zero-background).
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pub mask_margin: usize,

    /// With --proposals: the mask loss on rays counts an unsure proposal pixel within PX pixels
    /// of an instance to that instance (the nearest) instead of leaving it to the colour loss.
    /// The proposals leave a ring around each instance unsure, and that ring is mostly the
    /// object's own soft outline: a lone object is scored all or nothing by FG-ARI, so its slot
    /// must win that outline too (0 = off; `colf-train propose --claim` scores the result).
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pub mask_claim: usize,

    /// Mask losses also ignore background pixels darker than their view's floor by more than D
    /// (sRGB brightness in [0, 1]; the floor level is the median brightness of the view's
    /// background pixels): the hard shadows objects cast, which, like --mask-margin's band, are
    /// left to the colour loss and so to the objects' slots. For scenes on a uniform floor such
    /// as clevr567 (0 = off).
    #[arg(long, default_value_t = 0.0, value_name = "D")]
    pub mask_shadow_depth: f64,

    /// Render the background from a zero latent, so it cannot depend on the image (the paper's
    /// choice for CLEVR). A fresh model's setting, stored in its config (so encode and render
    /// do the same); with --init or --resume the model's own setting holds.
    #[arg(long)]
    pub zero_background: bool,

    /// Override a field of the model's config, KEY=VALUE (repeatable; keys as in
    /// docs/model.md, e.g. `--set ray_fourier_freqs=6`). With --init, only settings that keep
    /// every tensor's shape (e.g. `--set default_slots=10`) or that grow the model while keeping
    /// what it computes (`--set static_background=true` on a zero-background model, larger
    /// `hypernet_hidden`, `lfn_hidden`, `lfn_features`, `head_hidden`, `head_hidden_layers`,
    /// `compositor_hidden` or `compositor_hidden_layers` — e.g. the small decoder grown to the
    /// paper's —, `--set hypernet_per_layer=true` for a hidden layer per light-field layer in
    /// each hypernetwork, a wider `slot_dim` (see --slot-values), `--set
    /// zero_background=false` for a background that reads the image, more
    /// `floor_fourier_freqs` — e.g. `--set floor_fourier_freqs=5`, the background's features of
    /// where a ray meets the floor z = 0, read with zero weights at first; new
    /// weights drawn from --seed); ignored with --resume.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub config_overrides: Vec<String>,

    /// With --init and a wider `--set slot_dim=N`: keep each old value N/old times (`copies`,
    /// N a whole multiple of the old) or add values of their own that start at zero and that
    /// the hypernetworks read with fresh weights (`fresh`, any N; docs/model.md).
    #[arg(long, value_enum, default_value_t = SlotValues::Copies, value_name = "HOW")]
    pub slot_values: SlotValues,

    /// Seed of the data order, ray sampling, slot noise and (fresh models) initialisation.
    #[arg(long, default_value_t = 0, value_name = "S")]
    pub seed: u64,

    /// Write the model and checkpoint every N steps (and on SIGINT/SIGTERM, and at the end).
    #[arg(long, default_value_t = 500, value_name = "N")]
    pub checkpoint_every: u64,

    /// Also keep the model of every Nth step as OUT with .stepN before its .safetensors
    /// extension (m.safetensors -> m.step2000.safetensors), to rewind a run that later degrades
    /// (0: never).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub keep_every: u64,

    /// Held-out data evaluated during training (PSNR, FG-ARI, foreground share...).
    #[arg(long, value_name = "DIR")]
    pub eval_data: Option<std::path::PathBuf>,

    /// Evaluate every N steps (0: never).
    #[arg(long, default_value_t = 1000, value_name = "N")]
    pub eval_every: u64,

    /// Scenes of --eval-data used per evaluation.
    #[arg(long, default_value_t = 8, value_name = "N")]
    pub eval_scenes: usize,

    /// Use only the first N training scenes (overfitting checks).
    #[arg(long, value_name = "N")]
    pub max_scenes: Option<usize>,

    /// Keep the parameters whose names start with PREFIX fixed (repeatable; tensor names as in
    /// docs/model.md): e.g. `--freeze encoder. --freeze slot_attention.` adapts the decoder to a
    /// new look and keeps how the slots group pixels.
    #[arg(long, value_name = "PREFIX")]
    pub freeze: Vec<String>,

    /// Train the parameters whose names start with PREFIX at FACTOR times the learning rate
    /// (repeatable; a later one wins where prefixes overlap). Adam moves a weight by about the
    /// learning rate a step whatever its gradient, so this is how some layers learn faster than
    /// the rest: e.g. `--lr-scale hypernet_bg.fc1.weight=20` for the background's input weights
    /// grown at zero by `--set zero_background=false` (measured in docs/training-log.md, run b5:
    /// for that layer it did not help).
    #[arg(long, value_name = "PREFIX=FACTOR", value_parser = parse_lr_scale)]
    pub lr_scale: Vec<(String, f64)>,

    /// Decode through candle's autograd, the slow reference the fused decoder kernel is tested
    /// against, instead of the kernel: the same function (gradients agree to 1e-4), several
    /// times slower. For checking a run's curve, not for training.
    #[arg(long)]
    pub reference_decoder: bool,

    /// Abort after this many steps with a non-finite loss or gradient.
    #[arg(long, default_value_t = 50, value_name = "N")]
    pub max_bad_steps: u64,

    /// Print a progress line every N steps when stderr is not a terminal.
    #[arg(long, default_value_t = 50, value_name = "N")]
    pub print_every: u64,
}

/// The subcommands of colf-train.
#[derive(Subcommand, Debug)]
pub enum TrainCommand {
    // (Each subcommand's help is its Args struct's `about`/`long_about`: a doc comment here
    // would replace them.)
    Init(InitArgs),
    Plot(PlotArgs),
    Average(AverageArgs),
    Configure(ConfigureArgs),
    Info(InfoArgs),
    Propose(ProposeArgs),
}

/// `colf-train info`.
#[derive(Args, Debug)]
#[command(
    about = "Print a model's identity, size, config and how it was trained, as JSON",
    long_about = "Read MODEL (`-`: stdin) and print one JSON object on stdout: `file`, `identity`, \
`parameters`, `config` (as stored, with the default encoding under `inference`), `training` and \
`masks_used`. `training` lists the model's training runs, oldest first (a curriculum's stages, \
or the runs of the model it was fine-tuned from, then its own): the data folder and its renderer, \
the scenes, whether the data had masks (`masks_in_data`) and whether a loss or the ray sampling \
used them (`masks_used`), the model it started from, the steps, the batch, the learning-rate \
schedule and the loss weights. The bundled `supervised` model's file predates the records: its \
runs are written down from its recipe (`make model`), recognised by its identity, and each \
carries a `reconstructed` note; a model trained from it (such as the bundled `blender` model) \
lists them before its own. `unrecorded_init` is the identity of the model the first listed run \
started from when nothing records how that model was trained (a file written before \
colf-train recorded training, or a `colf-train init` file), else null. `masks_used` (top level) \
is true if any listed run used masks, false if none did and the list starts from a fresh model, \
and null when that is not known: no records (`training` is null too) or an unrecorded start.",
    after_help = "Examples:\n  colf-train info model.safetensors\n  colf-train info model.safetensors | jq '.training[] | {data, steps, masks_used}'"
)]
pub struct InfoArgs {
    /// The model file (`-`: stdin).
    #[arg(value_name = "MODEL")]
    pub model: String,
}

/// `colf-train propose`.
#[derive(Args, Debug)]
#[command(
    about = "Compute the object proposals --proposals trains on, write them and score them",
    long_about = "Compute, for every view of the first --scenes scenes of DIR, the object proposals `colf-train --proposals` uses in place of masks: a smooth floor (a cubic polynomial in the pixel coordinates, fitted by trimmed least squares) is fitted to the view; up to three walls (large regions of one chromaticity far from the floor and touching the border, each at least 5 % of the view) get quadratic surfaces of their own and the floor is refitted without them; pixels farther from their surface than 0.08 in some channel, and than 2.5 times the surface's own grain (the 75th percentile of its residuals: a wooden or tiled floor), are candidates, and those between the two are unsure unless their chromaticity is farther from the surface's than 4 times the surface's own chromaticity spread (an object of another hue on the grain); a candidate that is a uniformly darkened or brightened copy of the floor is lighting (a shadow, a bright spot); the other candidates are grouped into 8-connected instances whose neighbouring pixels have nearly the same chromaticity (so touching objects of different colours stay apart), fragments under 0.2 % of the view join the neighbour they share the longest border with, and the instances are numbered 1, 2, ... from the largest; lighting, instances under 0.1 % of the view and a one-pixel ring around each instance are unsure (255), which the mask losses leave to the colour loss. No mask file is read to make them. With --out, each view's proposals are written as an 8-bit grey PNG, OUT/SCENE/STEM.proposal.png (0 background, 1... instances, 255 unsure). Where the data has masks, they are then read to score the proposals: one JSON object on stdout with the means over views of fg_ari (the ARI over ground-truth object pixels, background and unsure counting as labels), fg_ari_on_instances (over the object pixels the instances cover), objects_called_background, objects_unsure, instances_on_background and unsure (shares of pixels), and instances (per view).",
    after_help = "Examples:\n  colf-train propose --data data/train --scenes 25\n  \
colf-train propose --data data/train --scenes 4 --out proposals/"
)]
pub struct ProposeArgs {
    /// The dataset (colf or uORF layout).
    #[arg(long, value_name = "DIR")]
    pub data: std::path::PathBuf,

    /// Only the first N scenes.
    #[arg(long, value_name = "N")]
    pub scenes: Option<usize>,

    /// Write each view's proposals as OUT/SCENE/STEM.proposal.png.
    #[arg(long, value_name = "DIR")]
    pub out: Option<std::path::PathBuf>,

    /// Propose against MODEL's background render instead (as `colf-train --proposals-against`).
    #[arg(long, value_name = "MODEL")]
    pub against: Option<std::path::PathBuf>,

    /// Count unsure pixels within PX pixels of an instance to it, as the mask losses of
    /// `colf-train --mask-claim PX` do (written and scored that way).
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pub claim: usize,
}

/// Runs `colf-train propose`.
pub fn run_propose(args: &ProposeArgs) -> anyhow::Result<()> {
    use crate::proposals::{is_instance, score, ProposalParams};
    let data = crate::dataset::Dataset::open(&args.data)?;
    let n = args.scenes.map_or(data.len(), |m| m.min(data.len()));
    let params = ProposalParams::default();
    let known = args
        .against
        .as_deref()
        .map(crate::train::known_background::KnownBackground::load)
        .transpose()?;
    let (mut scores, mut views, mut instances) = (Vec::new(), 0usize, 0usize);
    for i in 0..n {
        let scene = data.load(i)?;
        for view in &scene.views {
            // Made from the image alone (and the known background); the mask, where there is
            // one, only scores them.
            let ids =
                crate::train::known_background::view_proposals(known.as_ref(), view, &params)?;
            let (w, h) = (view.image.w as usize, view.image.h as usize);
            let ids = crate::proposals::claim_edges(&ids, w, h, args.claim);
            instances += ids
                .iter()
                .filter(|&&id| is_instance(id))
                .max()
                .copied()
                .unwrap_or(0) as usize;
            views += 1;
            if let Some(out) = &args.out {
                let stem = view
                    .path
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default();
                let dir = out.join(&scene.name);
                crate::io::create_folder_in_folder(&dir)?;
                let png = crate::image_io::encode_png_grey(view.image.w, view.image.h, &ids);
                crate::io::write_in_folder(&dir.join(format!("{stem}.proposal.png")), &png)?;
            }
            if let Some(mask) = &view.mask {
                let shown = view.path.display();
                scores.push(score(&ids, mask).map_err(|e| anyhow::anyhow!("{shown}: {e}"))?);
            }
        }
    }
    let mean = |f: &dyn Fn(&crate::proposals::ProposalScore) -> Option<f64>| {
        crate::metrics::mean_std(scores.iter().map(f)).0
    };
    let summary = serde_json::json!({
        "data": args.data.display().to_string(),
        "scenes": n,
        "views": views,
        "views_with_masks": scores.len(),
        "instances": if views == 0 { 0.0 } else { instances as f64 / views as f64 },
        "fg_ari": mean(&|s| s.fg_ari),
        "fg_ari_on_instances": mean(&|s| s.fg_ari_on_instances),
        "objects_called_background": mean(&|s| Some(s.objects_called_background)),
        "objects_unsure": mean(&|s| Some(s.objects_unsure)),
        "instances_on_background": mean(&|s| Some(s.instances_on_background)),
        "unsure": mean(&|s| Some(s.unsure)),
    });
    let text = serde_json::to_string_pretty(&summary)? + "\n";
    crate::io::write_output("-", text.as_bytes(), false)
}

/// Runs `colf-train info`.
pub fn run_info(args: &InfoArgs) -> anyhow::Result<()> {
    let name = crate::io::display_name(&args.model).to_string();
    let bytes = crate::io::read_input(&args.model, true)?;
    let model = crate::model::Colf::from_bytes(&bytes, &name)?;
    let info = crate::model::history::describe(&model, &name)?;
    let text = serde_json::to_string_pretty(&info)? + "\n";
    crate::io::write_output("-", text.as_bytes(), false)
}

/// `colf-train configure`.
#[derive(Args, Debug)]
#[command(
    about = "Change settings of a model's config that keep its weights",
    long_about = "Write MODEL to OUT (atomically; `-` for stdout, refused on a terminal) with config settings changed by --set KEY=VALUE (the value is JSON; keys as in docs/model.md). Only settings that keep every tensor's name and shape are accepted, so the weights are copied unchanged; the config, and so the identity, change. The main use is `inference`, the encoding colf-encode and colf-eval use with this model when their flags do not say, e.g. --set 'inference={\"slots\":12,\"tries\":4,\"refine\":50}' (--set inference=null removes it; --set inference.refine=50 changes one member of the model's own). --half writes every tensor of 16,384 values or more (all weight matrices but the smallest: over 99 % of a paper-sized decoder's values; the biases and norms stay f32) in IEEE half precision, about half the file; the weights are then rounded, so the identity changes and the scores should be checked (colf-eval). A model read with half tensors keeps them half when configured again. The new identity is printed on stderr.",
    after_help = "Examples:\n  colf-train configure stage6.safetensors --set 'inference={\"slots\":12,\"tries\":4,\"refine\":50}' -o model.safetensors\n  colf-train configure big.safetensors --half -o small.safetensors"
)]
pub struct ConfigureArgs {
    /// The model to change.
    #[arg(value_name = "MODEL")]
    pub model: std::path::PathBuf,

    /// A config setting to change, KEY=VALUE or SETTING.MEMBER=VALUE (repeatable).
    #[arg(
        long = "set",
        value_name = "KEY=VALUE",
        required_unless_present = "half"
    )]
    pub config_overrides: Vec<String>,

    /// Write the tensors of 16,384 values or more in half precision (IEEE f16).
    #[arg(long)]
    pub half: bool,

    /// Where to write the model (`-`: stdout).
    #[arg(short, long, value_name = "MODEL")]
    pub output: String,
}

/// `colf-train configure --half` stores tensors of at least this many values in half precision:
/// every weight matrix but the smallest. Biases and norms stay f32: they are few bytes, and a
/// rounded bias shifts every output of its layer alike.
pub const HALF_MIN_VALUES: usize = 1 << 14;

/// Runs `colf-train configure`.
pub fn run_configure(args: &ConfigureArgs) -> anyhow::Result<()> {
    let model = crate::model::Colf::load(&args.model)?;
    let name = args.model.display().to_string();
    let mut configured = model
        .configured(&args.config_overrides)
        .map_err(|e| anyhow::anyhow!("{name}: {e:#}"))?;
    if args.half {
        configured = configured
            .with_half_storage(HALF_MIN_VALUES)
            .map_err(|e| anyhow::anyhow!("{name}: {e:#}"))?;
    }
    let (bytes, identity) = configured.to_bytes()?;
    crate::io::write_output(&args.output, &bytes, true)?;
    eprintln!("colf-train: {name} configured, identity {identity}");
    Ok(())
}

/// `colf-train average`.
#[derive(Args, Debug)]
#[command(
    about = "Average the weights of several models of one run into one model",
    long_about = "Write the element-wise mean of the weights of MODEL... to OUT (atomically; `-` \
for stdout, refused on a terminal): a cheap ensemble of, e.g., the snapshots that --keep-every \
kept while the learning rate was still high, at the cost of one model. The models must share \
their config (runs continued from one another do; independently initialised models do not \
average into anything useful). The new model's identity is printed on stderr."
)]
pub struct AverageArgs {
    /// The models to average.
    #[arg(value_name = "MODEL", required = true)]
    pub models: Vec<std::path::PathBuf>,

    /// Where to write the averaged model (`-`: stdout).
    #[arg(short, long, value_name = "MODEL")]
    pub output: String,
}

/// Runs `colf-train average`: loads every model, averages, writes.
pub fn run_average(args: &AverageArgs) -> anyhow::Result<()> {
    let models = args
        .models
        .iter()
        .map(|path| crate::model::Colf::load(path))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let names: Vec<String> = args
        .models
        .iter()
        .map(|p| p.display().to_string())
        .collect();
    let named: Vec<(&str, &crate::model::Colf)> =
        names.iter().map(String::as_str).zip(&models).collect();
    let (bytes, identity) = crate::train::average::average(&named)?;
    crate::io::write_output(&args.output, &bytes, true)?;
    eprintln!(
        "colf-train: the mean of {} models, identity {identity}",
        models.len()
    );
    Ok(())
}

/// `colf-train plot`.
#[derive(Args, Debug)]
#[command(
    about = "Draw training curves from JSON-lines training logs, one run or several in one picture",
    long_about = "Draw the curves of a training log (OUT.log.jsonl, as colf-train writes it) \
into a PNG: loss (log scale); PSNR of the sampled rays and of the rays on objects; the share of \
object rays won by foreground slots and FG-ARI; and, when the log has evaluations, held-out \
novel-view PSNR and FG-ARI. Per-step values are drawn faint with a moving average on top.\n\n\
Several logs (at most 8) are drawn into the same panels for comparing runs, such as the fused \
decoder against --reference-decoder from one initialisation, or two recipes. Run i is drawn in \
colour i of a fixed palette in every panel, a panel's second series is dashed, and the step axis \
spans all runs. Legend entries read NAME: series, where NAME is the run's --label or else its \
log's file name without .log.jsonl (or .jsonl). A single log keeps per-series colours and \
unprefixed legend entries.",
    after_help = "Examples:\n  colf-train plot model.safetensors.log.jsonl -o curves.png\n  \
colf-train plot fused/m.safetensors.log.jsonl ref/m.safetensors.log.jsonl \\\n    \
--label fused --label reference -o compare.png"
)]
pub struct PlotArgs {
    /// The JSON-lines logs, at most 8 (`-`: stdin, for one of them).
    #[arg(value_name = "LOG", required = true)]
    pub logs: Vec<String>,

    /// Output PNG (`-`: stdout, refused on a terminal).
    #[arg(short, long, value_name = "PNG")]
    pub output: String,

    /// The legend name of a run: give it once per LOG, in the same order, or not at all
    /// (default: the log's file name without .log.jsonl).
    #[arg(long, value_name = "NAME")]
    pub label: Vec<String>,

    /// Width in pixels.
    #[arg(long, default_value_t = 1000, value_name = "W")]
    pub width: u32,

    /// Height in pixels.
    #[arg(long, default_value_t = 700, value_name = "H")]
    pub height: u32,
}

impl PlotArgs {
    /// The logs with their legend names. What clap cannot check (the number of logs and of
    /// labels, stdin used twice) is a usage error (exit 2).
    pub fn runs(&self) -> anyhow::Result<Vec<(&str, String)>> {
        let max = crate::train::plot::MAX_RUNS;
        let usage = |msg: String| Err(crate::cli::UsageError(msg).into());
        if self.logs.len() > max {
            return usage(format!(
                "at most {max} logs can be drawn in one picture, got {}",
                self.logs.len()
            ));
        }
        if !self.label.is_empty() && self.label.len() != self.logs.len() {
            return usage(format!(
                "--label given {} for {} LOG{}: give one --label per LOG, in order, or none",
                match self.label.len() {
                    1 => "once".to_string(),
                    n => format!("{n} times"),
                },
                self.logs.len(),
                if self.logs.len() == 1 { "" } else { "s" }
            ));
        }
        let stdins = self.logs.iter().filter(|log| crate::io::is_stdio(log));
        if stdins.count() > 1 {
            return usage("only one LOG can be stdin (`-`)".to_string());
        }
        let label = |i: usize, log: &str| match self.label.get(i) {
            Some(name) => name.clone(),
            None => crate::train::plot::default_label(log),
        };
        Ok(self
            .logs
            .iter()
            .enumerate()
            .map(|(i, log)| (log.as_str(), label(i, log)))
            .collect())
    }
}

/// Runs `colf-train plot`.
pub fn run_plot(args: &PlotArgs) -> anyhow::Result<()> {
    crate::train::plot::plot_files(&args.runs()?, &args.output, args.width, args.height)
}

/// `colf-train init`.
#[derive(Args, Debug)]
#[command(
    about = "Write a freshly initialised colf model",
    long_about = "Write a freshly initialised colf model to OUT (atomically; `-` for stdout, \
refused on a terminal). The same --preset and --seed give a byte-identical file. The model's \
parameter count and identity are printed on stderr."
)]
pub struct InitArgs {
    /// Size preset (`volumetric`: the uORF-style volumetric baseline decoder on the small
    /// encoder, for speed comparisons; it renders but does not train).
    #[arg(long, value_name = "PRESET", value_parser = ["small", "paper", "volumetric"], default_value = "small")]
    pub preset: String,

    /// Seed of the weight initialisation.
    #[arg(long, default_value_t = 0, value_name = "S")]
    pub seed: u64,

    /// Override a field of the preset's config, KEY=VALUE (repeatable; keys as in
    /// docs/model.md, e.g. `--set ray_fourier_freqs=6`).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub config_overrides: Vec<String>,

    /// Where to write the model (`-`: stdout).
    #[arg(short, long, value_name = "MODEL")]
    pub output: String,
}

/// Runs a training run with progress on stderr.
impl RunArgs {
    /// The library's training options; the output path is checked for writability now, so
    /// a bad path fails before training, not after.
    pub fn train_options(&self) -> anyhow::Result<crate::train::trainer::TrainOptions> {
        use crate::train::trainer::TrainOptions;
        let args = self;
        let (Some(data), Some(out)) = (args.data.clone(), args.out.clone()) else {
            anyhow::bail!("--data and --out are required");
        };
        crate::io::check_writable(&out)?;
        Ok(TrainOptions {
            data,
            out,
            init: args
                .init
                .as_deref()
                .map(|m| crate::cli::model_path::resolve_model_path(Some(m)))
                .transpose()?,
            preset: args.preset.clone(),
            steps: args.steps,
            batch_scenes: args.batch,
            views_per_scene: args.views,
            context_views: args.context_views.clone(),
            rays_per_view: args.rays,
            slots: args.slots,
            lr: args.lr,
            warmup: args.warmup,
            decay_from: args.decay_from,
            final_lr: args.final_lr,
            l1_weight: args.l1_weight,
            latent_weight: args.latent_weight,
            mask_weight: args.mask_weight,
            attention_mask_weight: args.attention_mask_weight,
            object_fraction: args.object_fraction,
            mask_margin: args.mask_margin,
            mask_claim: args.mask_claim,
            mask_shadow_depth: args.mask_shadow_depth,
            zero_background: args.zero_background,
            config_overrides: args.config_overrides.clone(),
            slot_values: args.slot_values,
            seed: args.seed,
            checkpoint_every: args.checkpoint_every,
            keep_every: args.keep_every,
            eval_every: args.eval_every,
            eval_data: args.eval_data.clone(),
            eval_scenes: args.eval_scenes,
            max_bad_steps: args.max_bad_steps,
            max_scenes: args.max_scenes,
            freeze: args.freeze.clone(),
            lr_scale: args.lr_scale.clone(),
            proposals: args.proposals || args.proposals_against.is_some(),
            proposals_against: args.proposals_against.clone(),
            reference_decoder: args.reference_decoder,
        })
    }
}

/// `--lr-scale PREFIX=FACTOR`: the factor must be a positive, finite number.
fn parse_lr_scale(text: &str) -> Result<(String, f64), String> {
    let (prefix, factor) = text
        .rsplit_once('=')
        .ok_or_else(|| format!("`{text}` is not PREFIX=FACTOR"))?;
    match factor.trim().parse::<f64>() {
        Ok(f) if f > 0.0 && f.is_finite() && !prefix.is_empty() => Ok((prefix.to_string(), f)),
        _ => Err(format!(
            "`{text}`: PREFIX=FACTOR needs a parameter-name prefix and a positive factor"
        )),
    }
}

/// One progress line of a training log line: an evaluation, or the step's figures.
fn progress_text(line: &serde_json::Value) -> String {
    let step = line["step"].as_u64().unwrap_or(0);
    if let Some(eval) = line.get("eval") {
        return format!("eval @ {step}: {eval}");
    }
    // Figures a run cannot measure (those on object rays, without masks or proposals) are
    // null in the log and left out here, rather than printed as NaN.
    let mut text = String::new();
    for (label, key, decimals) in [
        ("loss", "loss", 5),
        ("psnr", "psnr", 2),
        ("obj", "obj_psnr", 2),
        ("fg", "fg_share", 3),
        ("fg-ari", "fg_ari", 3),
        ("slots", "slots_used", 1),
    ] {
        if let Some(v) = line[key].as_f64() {
            text += &format!("{label} {v:.decimals$} ");
        }
    }
    match line["rays_per_s"].as_f64() {
        Some(v) => text + &format!("{v:.0} rays/s"),
        None => text.trim_end().to_string(),
    }
}

pub fn run_training(args: &RunArgs) -> anyhow::Result<()> {
    use crate::train::trainer::Trainer;
    use std::io::{IsTerminal, Write};

    let opts = args.train_options()?;
    if args.resume {
        if let Some(step) = crate::train::trainer::finished_step(&opts)? {
            eprintln!(
                "colf-train: {} is done (its checkpoint is at step {step} of {}); nothing to train",
                opts.out.display(),
                args.steps
            );
            return Ok(());
        }
    }
    // The first SIGINT/SIGTERM stops training at the end of the step, after a checkpoint.
    let stop = crate::io::defer_signals();
    let mut trainer = Trainer::new(opts, args.resume)?;
    let log_path = trainer.opts.log_path();
    let mut log_file = crate::io::open_log_in_folder(&log_path)?;
    eprintln!(
        "colf-train: {} scenes, {} parameters, step {} of {}, log {}",
        trainer.num_scenes(),
        trainer.model().num_parameters(),
        trainer.step,
        args.steps,
        log_path.display()
    );
    let bar = std::io::stderr().is_terminal().then(|| {
        let bar = indicatif::ProgressBar::new(args.steps);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{bar:30} {pos}/{len} {msg} [{elapsed} < {eta}]",
            )
            .expect("template"),
        );
        bar.set_position(trainer.step);
        bar
    });
    let print_every = args.print_every.max(1);
    let mut write_error = None;
    trainer.run(stop, |line| {
        if write_error.is_none() {
            if let Err(e) = writeln!(log_file, "{line}") {
                write_error = Some(e);
            }
        }
        let step = line["step"].as_u64().unwrap_or(0);
        let text = progress_text(line);
        match &bar {
            Some(bar) => {
                bar.set_position(step + 1);
                if line.get("eval").is_some() {
                    bar.println(text);
                } else {
                    bar.set_message(text);
                }
            }
            None => {
                if line.get("eval").is_some() || (step + 1) % print_every == 0 {
                    eprintln!("colf-train: step {} {text}", step + 1);
                }
            }
        }
    })?;
    if let Some(bar) = bar {
        bar.finish();
    }
    if let Some(e) = write_error {
        anyhow::bail!("{}: writing the log failed: {e}", log_path.display());
    }
    eprintln!(
        "colf-train: stopped at step {} ({}); model {}, checkpoint {}",
        trainer.step,
        if trainer.step >= args.steps {
            "done"
        } else {
            "interrupted"
        },
        trainer.opts.out.display(),
        trainer.opts.checkpoint_path().display()
    );
    // Checkpointed; the exit status still says the run was stopped (130, 143).
    match crate::io::pending_signal() {
        Some(interrupted) => Err(interrupted.into()),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plot_args(args: &[&str]) -> PlotArgs {
        let all = [&["colf-train", "plot"], args].concat();
        match TrainArgs::try_parse_from(all).unwrap().command {
            Some(TrainCommand::Plot(plot)) => plot,
            other => panic!("{other:?}"),
        }
    }

    fn plot_usage_error(args: &[&str]) -> String {
        let err = plot_args(args).runs().unwrap_err();
        assert!(
            err.downcast_ref::<crate::cli::UsageError>().is_some(),
            "{err}"
        );
        err.to_string()
    }

    #[test]
    fn plot_labels_match_the_logs_or_default_to_file_names() {
        let runs = plot_args(&["a/x.log.jsonl", "b/y.jsonl", "-o", "p.png"]);
        assert_eq!(
            runs.runs().unwrap(),
            vec![("a/x.log.jsonl", "x".into()), ("b/y.jsonl", "y".into())]
        );
        let named = plot_args(&[
            "a.log.jsonl",
            "-",
            "--label",
            "fused",
            "--label",
            "ref",
            "-o",
            "p",
        ]);
        assert_eq!(
            named.runs().unwrap(),
            vec![("a.log.jsonl", "fused".into()), ("-", "ref".into())]
        );
        let err = plot_usage_error(&["a", "b", "--label", "x", "-o", "p"]);
        assert!(err.contains("--label given once for 2 LOGs"), "{err}");
        let err = plot_usage_error(&["a", "--label", "x", "--label", "y", "-o", "p"]);
        assert!(err.contains("--label given 2 times for 1 LOG:"), "{err}");
        let nine: Vec<String> = (0..9).map(|i| format!("{i}.log.jsonl")).collect();
        let mut args: Vec<&str> = nine.iter().map(String::as_str).collect();
        args.extend(["-o", "p"]);
        let err = plot_usage_error(&args);
        assert!(err.contains("at most 8 logs"), "{err}");
        let err = plot_usage_error(&["-", "-", "-o", "p"]);
        assert!(err.contains("only one LOG can be stdin"), "{err}");
        assert!(TrainArgs::try_parse_from(["colf-train", "plot", "-o", "p"]).is_err());
    }

    #[test]
    fn progress_lines_leave_out_what_a_run_cannot_measure() {
        let full = serde_json::json!({"step": 3, "loss": 0.5, "psnr": 20.0, "obj_psnr": 15.0,
            "fg_share": 0.9, "fg_ari": 0.8, "slots_used": 6.5, "rays_per_s": 1000.4});
        assert_eq!(
            progress_text(&full),
            "loss 0.50000 psnr 20.00 obj 15.00 fg 0.900 fg-ari 0.800 slots 6.5 1000 rays/s"
        );
        let unlabelled = serde_json::json!({"step": 3, "loss": 0.5, "psnr": 20.0,
            "obj_psnr": null, "fg_share": null, "fg_ari": null, "slots_used": 7.0,
            "rays_per_s": 1000.0});
        assert_eq!(
            progress_text(&unlabelled),
            "loss 0.50000 psnr 20.00 slots 7.0 1000 rays/s"
        );
        assert!(!progress_text(&unlabelled).contains("NaN"));
    }
}
