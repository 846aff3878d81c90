//! `colf-eval`: metrics of a rendered image or mask against its ground truth, as JSON.
//!
//! The dataset mode of DESIGN.md (`colf-eval --data DIR [--model M] [--scenes N]`) is meant to
//! be added to [`EvalArgs`] as top-level options next to an optional subcommand: make
//! `command` an `Option<EvalCommand>`, add the `--data`/`--model`/`--scenes` fields, and set
//! `args_conflicts_with_subcommands = true` so `images` and `masks` keep their exact syntax.

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
Either file may be `-` (stdin), not both. Images of different sizes are an error.",
    after_help = "Examples:\n  colf-eval images renders/frame_0000.png data/scene_00000/view_001.png\n  \
colf-eval masks renders/frame_0000.mask.png data/scene_00000/view_001.mask.png\n  \
colf-eval images a.png b.png | jq .psnr",
    subcommand_required = true,
    arg_required_else_help = true
)]
pub struct EvalArgs {
    #[command(subcommand)]
    pub command: EvalCommand,
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
        bail!("PRED and GT cannot both be stdin");
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
    let json = match &args.command {
        EvalCommand::Images { pred, gt } => serde_json::to_string(&eval_images(pred, gt)?)?,
        EvalCommand::Masks { pred, gt } => serde_json::to_string(&eval_masks(pred, gt)?)?,
    };
    write_output("-", (json + "\n").as_bytes(), false)
}
