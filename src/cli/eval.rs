//! `colf-eval`: metrics of a rendered image or mask against its ground truth, as JSON.
//!
//! The dataset mode (`colf-eval --data DIR [--model M] [--scenes N]`) is a set of top-level
//! options beside the optional subcommand (`args_conflicts_with_subcommands`), so `images` and
//! `masks` keep their exact syntax.

use crate::image_io::{read_labels, read_rgb};
use crate::io::{display_name, write_output};
use crate::metrics::{ImageScores, MaskScores};
use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};

/// Compare renders with ground truth: PSNR and SSIM of images, ARI and FG-ARI of masks.
#[derive(Parser, Debug)]
#[command(
    name = "colf-eval",
    version,
    about = "Compare renders and masks with ground truth: PSNR, SSIM, ARI, FG-ARI",
    long_about = "Compare a rendered image or segmentation mask with its ground truth and print \
the metrics as one line of JSON on stdout. The definitions follow uORF (and scikit-image / \
scikit-learn):\n\n\
PSNR is taken over all RGB values in [0, 1] (8-bit value / 255, alpha dropped): \
10 log10(1 / MSE) dB. Identical images have an infinite PSNR, which JSON cannot hold: it is \
printed as null.\n\n\
SSIM uses an 11x11 Gaussian window (sigma 1.5), k1 = 0.01, k2 = 0.03, data range 1, population \
covariances; the SSIM map is averaged over the valid region only (5 pixels are dropped at every \
border), then over the three channels. Images must be at least 11x11.\n\n\
ARI is scikit-learn's adjusted_rand_score of the two label maps; FG-ARI is the same over the \
pixels whose ground-truth label is not 0 (background), and null when the ground truth has no \
such pixel. Grey masks give the grey value as the label; colour masks give one label per \
distinct colour, black being 0.\n\n\
Either file may be `-` (stdin), not both. Images of different sizes are an error.\n\n\
With --data DIR (a colf-synth or uORF-layout dataset), the uORF protocol: per scene, view 0 is \
encoded (slots placed with view 0's camera) and every view rendered; ARI and FG-ARI are taken \
on view 0; PSNR, SSIM, NV-ARI and NV-FG-ARI are averaged over the other views. NV-ARI is \
uORF's (models/uorf_eval_model.py), as the published CLEVR-567 tables use it: the ARI of the \
full label maps of a novel view, background included; nv_fg_ari is the FG-ARI of the novel \
views, a different number. Each score is averaged over the scenes where it is defined, and its \
population standard deviation over those scenes is reported as NAME_std. --seeds N repeats the \
evaluation with N encoding seeds (S, S + 1000, ...): each score is then the mean of the runs' \
means, NAME_seed_std the standard deviation of the runs' means, and per_seed lists each run's \
summary. Also reported: input_psnr \
(view 0's reconstruction), object_psnr and background_psnr (the novel views' PSNR over their \
ground-truth object pixels and over the rest, each averaged over the views where its region has \
pixels), fg_share (share of ground-truth object pixels won by foreground \
slots), slots_used (foreground slots that win a pixel of view 0) and slots_kept (foreground slots in the encoding, after --redundant dropped those view 0 does not need). Where some scored views show a single object, whose FG-ARI is all or nothing (0 as soon as two \
labels share its pixels), the FG-ARI is also split: fg_ari_multi and nv_fg_ari_multi over the views \
with two objects or more, lone_object_views and nv_lone_object_views counting the single-object \
views, lone_object_whole_share and nv_lone_object_whole_share the share of them whose object one label \
wins whole (FG-ARI 1; the background's label counts, as in FG-ARI). View 0 is encoded as \
colf-encode would: with the model's default encoding (its slots, tries and refinement steps on \
view 0, see colf-encode(1); view 0 only, so the novel views stay unseen), or as --slots, \
--tries, --refine and --fast (one pass) say. The JSON records slots, tries, refine_steps, redundant_mse and, \
when refining, the refine settings. The JSON object goes to stdout; --per-scene adds a `per_scene` array, --renders DIR writes each scene's renders and \
masks for inspection, and a progress line per scene goes to stderr (-q silences it). \
--journal FILE appends each scene's scores to FILE (JSON lines: a header naming the model, data \
and options, then one row a scene) as soon as the scene is done; run again with the same \
arguments, colf-eval reads the rows back, scores only the scenes after them and prints the \
same JSON as a run that was never stopped (--renders then holds only the scenes of the later \
run). A journal written for another model, data set or options is refused, not overwritten.\n\n\
--input-views 0,1,2 encodes those views of each scene together, as colf-encode does with \
several images (each view encoded, slots drawing the same object matched into one, all views \
refined at once, by default with twice the model's refinement steps): input_psnr, ARI and FG-ARI are then averaged over the input views, PSNR, \
SSIM and the NV scores over the other views, and the JSON gains input_views, \
objects_seen_twice (ground-truth objects that at least two input views show, 10 pixels or \
more in each) and one_slot_share (the share of those that exactly one slot draws: the same \
slot, and no other, wins at least a quarter of the object's pixels in every input view that \
shows it), and no_slot_share (the share of them that no slot draws). --novel-views 3 scores only view 3 as a novel view (recorded as novel_views), so \
one and three input views can be compared on the same held-out view.",
    after_help = "Examples:\n  colf-eval images renders/frame_0000.png data/scene_00000/view_001.png\n  \
colf-eval masks renders/frame_0000.mask.png data/scene_00000/view_001.mask.png\n  \
colf-eval images a.png b.png | jq .psnr\n  \
colf-eval --data data/test --scenes 100 > metrics.json\n  \
colf-eval --data data/test --fast > one-pass.json\n  \
colf-eval --data data/test --journal test.journal > metrics.json\n  \
colf-eval --data data/test --input-views 0,1,2 --novel-views 3 > three-views.json",
    args_conflicts_with_subcommands = true,
    arg_required_else_help = true
)]
pub struct EvalArgs {
    #[command(subcommand)]
    pub command: Option<EvalCommand>,

    /// Evaluate a model on a dataset (uORF protocol) instead of comparing two files.
    #[arg(long, value_name = "DIR")]
    pub data: Option<std::path::PathBuf>,

    /// Model file, or a bundled model's name (`default`, `supervised`, `blender`); default: $COLF_MODEL, else
    /// the bundled default model.
    #[arg(long, value_name = "M", requires = "data")]
    pub model: Option<String>,

    /// Evaluate only the first N scenes.
    #[arg(long, value_name = "N", requires = "data")]
    pub scenes: Option<usize>,

    /// Foreground slots to encode with (default: the model's).
    #[arg(long, value_name = "K", requires = "data")]
    pub slots: Option<usize>,

    /// Seed of the slot noise.
    #[arg(long, default_value_t = 0, value_name = "S", requires = "data")]
    pub seed: u64,

    /// Run the whole evaluation N times with encoding seeds S, S + 1000, S + 2000, … and report
    /// the mean over the runs, the standard deviation over scenes of all runs (`*_std`) and
    /// over the N runs' means (`*_seed_std`), with each run's summary in `per_seed`.
    #[arg(long, default_value_t = 1, value_name = "N", requires = "data",
          value_parser = clap::value_parser!(u32).range(1..=100))]
    pub seeds: u32,

    #[command(flatten)]
    pub fit: crate::cli::FitArgs,

    /// Encode these views of each scene together (comma-separated indices, as colf-encode
    /// does with several images) and score the other views as novel views.
    #[arg(long, value_name = "V,...", value_delimiter = ',', default_values_t = [0usize],
          requires = "data")]
    pub input_views: Vec<usize>,

    /// Score only these views as novel views (comma-separated; default: every view that is
    /// not an input), e.g. the same held-out view for one and for three input views.
    #[arg(long, value_name = "V,...", value_delimiter = ',', requires = "data")]
    pub novel_views: Option<Vec<usize>>,

    /// Add the per-scene rows to the JSON.
    #[arg(long, requires = "data")]
    pub per_scene: bool,

    /// Write every scene's renders (SCENE_vN.png, SCENE_vN.mask.png) into this folder.
    #[arg(long, value_name = "DIR", requires = "data")]
    pub renders: Option<std::path::PathBuf>,

    /// Append each scene's scores to this journal as it is done, and on a later run with the
    /// same model, data and options continue after the scenes it holds (a long evaluation
    /// stopped part way resumes). A journal of another evaluation is refused.
    #[arg(long, value_name = "FILE", requires = "data")]
    pub journal: Option<std::path::PathBuf>,

    /// No progress lines on stderr.
    #[arg(short, long, requires = "data")]
    pub quiet: bool,
}

#[derive(Subcommand, Debug)]
pub enum EvalCommand {
    /// PSNR and SSIM of a colour image against the ground truth: {"psnr": ..., "ssim": ...}.
    Images {
        /// The predicted (rendered) PNG (`-`: stdin).
        #[arg(value_name = "PRED.png")]
        pred: String,
        /// The ground-truth PNG (`-`: stdin).
        #[arg(value_name = "GT.png")]
        gt: String,
    },
    /// ARI and FG-ARI of a segmentation mask against the ground truth: {"ari": ..., "fg_ari": ...}.
    Masks {
        /// The predicted mask PNG (`-`: stdin).
        #[arg(value_name = "PRED.mask.png")]
        pred: String,
        /// The ground-truth mask PNG; label 0 is background (`-`: stdin).
        #[arg(value_name = "GT.mask.png")]
        gt: String,
    },
}

fn check_inputs(pred: &str, gt: &str) -> Result<()> {
    if pred == "-" && gt == "-" {
        return Err(crate::cli::both_stdin("PRED", "GT"));
    }
    Ok(())
}

fn check_sizes(pred: &str, pred_wh: (u32, u32), gt: &str, gt_wh: (u32, u32)) -> Result<()> {
    if pred_wh != gt_wh {
        bail!(
            "{} is {}x{} but {} is {}x{}: the images must be the same size",
            display_name(pred),
            pred_wh.0,
            pred_wh.1,
            display_name(gt),
            gt_wh.0,
            gt_wh.1
        );
    }
    Ok(())
}

/// PSNR and SSIM of the colour PNGs `pred` and `gt`.
pub fn eval_images(pred: &str, gt: &str) -> Result<ImageScores> {
    check_inputs(pred, gt)?;
    let p = read_rgb(pred)?;
    let g = read_rgb(gt)?;
    check_sizes(pred, (p.w, p.h), gt, (g.w, g.h))?;
    ImageScores::compute(&p.data, &g.data, p.w as usize, p.h as usize)
        .with_context(|| format!("{} vs {}", display_name(pred), display_name(gt)))
}

/// ARI and FG-ARI of the mask PNGs `pred` and `gt`.
pub fn eval_masks(pred: &str, gt: &str) -> Result<MaskScores> {
    check_inputs(pred, gt)?;
    let (pw, ph, p) = read_labels(pred)?;
    let (gw, gh, g) = read_labels(gt)?;
    check_sizes(pred, (pw, ph), gt, (gw, gh))?;
    MaskScores::compute(&p, &g)
        .with_context(|| format!("{} vs {}", display_name(pred), display_name(gt)))
}

/// Runs `colf-eval`.
pub fn run(args: &EvalArgs) -> Result<()> {
    let json = match (&args.command, &args.data) {
        (Some(EvalCommand::Images { pred, gt }), _) => {
            serde_json::to_string(&eval_images(pred, gt)?)?
        }
        (Some(EvalCommand::Masks { pred, gt }), _) => {
            serde_json::to_string(&eval_masks(pred, gt)?)?
        }
        (None, Some(data)) => eval_dataset(args, data)?,
        (None, None) => bail!("give `images`, `masks` or --data DIR (see --help)"),
    };
    write_output("-", (json + "\n").as_bytes(), false)
}

/// How far apart the encoding seeds of `--seeds` runs are: a run's tries use seeds S … S + tries
/// − 1, so runs must not share them.
const SEED_STRIDE: u64 = 1000;

/// Writes a scene's renders and masks into `dir` as SCENE_vN.png and SCENE_vN.mask.png.
fn write_renders(
    dir: &std::path::Path,
    scene: &str,
    renders: &[crate::render::output::FrameRender],
) -> Result<()> {
    for (v, frame) in renders.iter().enumerate() {
        let base = dir.join(format!("{scene}_v{v}"));
        let png = crate::image_io::encode_png_rgb(frame.width, frame.height, &frame.rgb);
        crate::io::write_in_folder(&base.with_extension("png"), &png)?;
        crate::io::write_in_folder(&base.with_extension("mask.png"), &frame.mask_png()?)?;
    }
    Ok(())
}

/// What a journal's rows were scored with (`options`: the first run's encoding): a journal is
/// only read back by the same evaluation (the encoding seed is each row's own).
fn journal_identity(
    args: &EvalArgs,
    data: &std::path::Path,
    model: &crate::model::Colf,
    scenes: usize,
    options: &crate::encode::EncodeOptions,
) -> Result<serde_json::Value> {
    let data = std::fs::canonicalize(data).unwrap_or_else(|_| data.to_path_buf());
    Ok(serde_json::json!({
        "colf": env!("CARGO_PKG_VERSION"),
        "data": data.display().to_string(),
        "model": model.identity()?,
        "scenes": scenes,
        "seed": args.seed,
        "seeds": args.seeds,
        "input_views": args.input_views,
        "novel_views": args.novel_views,
        "encoding": {
            "slots": options.num_slots,
            "prune_mass": options.prune_mass,
            "tries": options.tries,
            "refine": options.refine,
            "redundant_mse": options.redundant_mse,
            "agreed_slots": options.agreed_slots,
            "triangulate_steps": options.triangulate_steps,
        },
    }))
}

/// Takes the journal's rows of the run with encoding seed `seed` out of `rows`: they must be the
/// first scenes, in order (a journal is written one scene after the other).
fn take_run_rows(
    rows: &mut Vec<crate::evaluate::journal::JournalRow>,
    seed: u64,
    journal: Option<&std::path::Path>,
) -> Result<Vec<crate::evaluate::SceneScores>> {
    let (mine, rest): (Vec<_>, Vec<_>) = std::mem::take(rows)
        .into_iter()
        .partition(|r| r.seed == seed);
    *rows = rest;
    if let Some(pos) = mine.iter().enumerate().position(|(i, r)| r.index != i) {
        bail!(
            "{}: row {} of seed {seed} is scene {}, not scene {pos}: the journal is out of order",
            journal.map_or("journal".into(), |p| p.display().to_string()),
            pos + 1,
            mine[pos].index
        );
    }
    Ok(mine.into_iter().map(|r| r.scores).collect())
}

/// `colf-eval --data DIR`: the uORF protocol over a dataset; returns the JSON text.
fn eval_dataset(args: &EvalArgs, data: &std::path::Path) -> Result<String> {
    let dataset = crate::dataset::Dataset::open(data)?;
    if dataset.is_empty() {
        bail!("{}: no scenes found", data.display());
    }
    if let Some(error) = crate::evaluate::input_views_error(&args.input_views) {
        return Err(crate::cli::UsageError(format!("--input-views: {error}")).into());
    }
    let protocol = crate::evaluate::Protocol {
        inputs: args.input_views.clone(),
        novel: args.novel_views.clone(),
    };
    let model = crate::cli::model_path::load_model(args.model.as_deref())?;
    if let Some(dir) = &args.renders {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("{}: cannot create the folder", dir.display()))?;
    }
    let total = args.scenes.map_or(dataset.len(), |n| n.min(dataset.len()));
    let views = args.input_views.len();
    // The first run's encoding (seed S), as the JSON records it.
    let options = args
        .fit
        .encode_options_for_views(model.config(), args.slots, args.seed, views);
    let (mut journal, mut journal_rows) = match &args.journal {
        Some(path) => {
            let identity = journal_identity(args, data, &model, total, &options)?;
            let (journal, rows) = crate::evaluate::journal::Journal::open(path, &identity)?;
            if !args.quiet && !rows.is_empty() {
                eprintln!(
                    "colf-eval: {}: {} scene{} scored before, not scored again",
                    path.display(),
                    rows.len(),
                    if rows.len() == 1 { "" } else { "s" }
                );
            }
            (Some(journal), rows)
        }
        None => (None, Vec::new()),
    };
    let started = std::time::Instant::now();
    let mut runs = Vec::new();
    let mut all_rows = Vec::new();
    for run in 0..args.seeds as u64 {
        let seed = args.seed.wrapping_add(run * SEED_STRIDE);
        let run_options =
            args.fit
                .encode_options_for_views(model.config(), args.slots, seed, views);
        let done = take_run_rows(&mut journal_rows, seed, args.journal.as_deref())?;
        let (scores, rows) = crate::evaluate::evaluate(
            &model,
            &dataset,
            args.scenes,
            &protocol,
            &run_options,
            done,
            |i, row, renders| {
                // The first run's renders: what --renders shows.
                if let (Some(dir), 0) = (&args.renders, run) {
                    write_renders(dir, &row.scene, renders)?;
                }
                if let Some(journal) = &mut journal {
                    journal.append(&crate::evaluate::journal::JournalRow {
                        seed,
                        index: i,
                        scores: row.clone(),
                    })?;
                }
                if !args.quiet {
                    let show = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.3}"));
                    let of_run = if args.seeds > 1 {
                        format!(" (seed {seed})")
                    } else {
                        String::new()
                    };
                    eprintln!(
                        "colf-eval: {}/{total}{of_run} {} psnr {} fg-ari {} ({:.1} s)",
                        i + 1,
                        row.scene,
                        show(row.psnr),
                        show(row.fg_ari),
                        started.elapsed().as_secs_f64()
                    );
                }
                Ok(())
            },
        )?;
        runs.push((seed, scores));
        all_rows.extend(rows);
    }
    let encoding = args
        .fit
        .encoding_for_views(model.config(), args.slots, views);
    let scores = crate::evaluate::DatasetScores::from_scenes(&all_rows);
    let rows = all_rows;
    let mut doc = serde_json::to_value(&scores)?;
    doc["data"] = serde_json::json!(data.display().to_string());
    doc["model"] = serde_json::json!(model.identity()?);
    doc["slots"] = serde_json::json!(encoding.slots);
    doc["tries"] = serde_json::json!(encoding.tries);
    doc["refine_steps"] = serde_json::json!(encoding.refine);
    doc["redundant_mse"] = serde_json::json!(options.redundant_mse);
    if args.input_views != [0] {
        doc["input_views"] = serde_json::json!(args.input_views);
    }
    if let Some(novel) = &args.novel_views {
        doc["novel_views"] = serde_json::json!(novel);
    }
    if options.refine.steps > 0 {
        doc["refine"] = serde_json::to_value(options.refine)?;
    }
    if args.seeds > 1 {
        // Over the runs' means (each run scores the same scenes).
        doc["scenes"] = serde_json::json!(runs[0].1.scenes);
        doc["seeds"] = serde_json::json!(args.seeds);
        for name in crate::evaluate::QUALITY_SCORES {
            let means = runs
                .iter()
                .map(|(_, r)| serde_json::to_value(r).ok()?[name].as_f64());
            let (_, std) = crate::metrics::mean_std(means);
            doc[format!("{name}_seed_std")] = serde_json::json!(std);
        }
        let per_seed: Vec<serde_json::Value> = runs
            .iter()
            .map(|(seed, r)| {
                let mut v = serde_json::to_value(r).expect("scores serialise");
                v["seed"] = serde_json::json!(seed);
                v
            })
            .collect();
        doc["per_seed"] = serde_json::json!(per_seed);
    }
    if args.per_scene {
        doc["per_scene"] = serde_json::to_value(&rows)?;
    }
    Ok(serde_json::to_string(&doc)?)
}
