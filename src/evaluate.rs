//! The uORF evaluation protocol on a dataset: per scene, view 0 is encoded (slots placed with
//! view 0's camera), every view is rendered; ARI and FG-ARI are taken on view 0, PSNR, SSIM,
//! NV-ARI and NV-FG-ARI averaged over the other views; then the mean (and the standard
//! deviation) over scenes.
//!
//! NV-ARI is uORF's (`models/uorf_eval_model.py`), as every published CLEVR-567 table uses it:
//! the adjusted Rand index of the full label maps of a novel view, background included. The
//! FG-ARI of the novel views (ground-truth object pixels only) is a different number and is
//! reported as `nv_fg_ari`.

use crate::codes::Codes;
use crate::dataset::{Dataset, SceneData};
use crate::encode::{encode_image, EncodeOptions};
use crate::metrics::{ari, fg_ari, mean_std, psnr, ssim};
use crate::model::Colf;
use crate::render::output::FrameRender;
use crate::render::PreparedScene;
use anyhow::{bail, Context, Result};
use serde::Serialize;

/// Scores of one scene. `None` where a score is undefined (no masks, or no foreground pixel).
#[derive(Clone, Debug, Default, Serialize)]
pub struct SceneScores {
    pub scene: String,
    /// Mean PSNR of the novel views (dB).
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    /// PSNR of the input view's reconstruction.
    pub input_psnr: Option<f64>,
    pub ari: Option<f64>,
    pub fg_ari: Option<f64>,
    /// ARI of the novel views' full label maps (background included, as uORF), averaged.
    pub nv_ari: Option<f64>,
    /// FG-ARI of the novel views, averaged.
    pub nv_fg_ari: Option<f64>,
    /// Share of ground-truth object pixels (all views) that foreground slots win.
    pub fg_share: Option<f64>,
    /// Foreground slots that win at least one pixel of the input view.
    pub slots_used: usize,
    /// Foreground slots in the encoding (after redundant slots were dropped).
    pub slots_kept: usize,
}

/// Means over scenes (each over the scenes where the score is defined), and for the quality
/// scores the population standard deviation over the same scenes (`*_std`).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct DatasetScores {
    pub scenes: usize,
    pub psnr: Option<f64>,
    pub psnr_std: Option<f64>,
    pub ssim: Option<f64>,
    pub ssim_std: Option<f64>,
    pub input_psnr: Option<f64>,
    pub input_psnr_std: Option<f64>,
    pub ari: Option<f64>,
    pub ari_std: Option<f64>,
    pub fg_ari: Option<f64>,
    pub fg_ari_std: Option<f64>,
    pub nv_ari: Option<f64>,
    pub nv_ari_std: Option<f64>,
    pub nv_fg_ari: Option<f64>,
    pub nv_fg_ari_std: Option<f64>,
    pub fg_share: Option<f64>,
    pub slots_used: f64,
    pub slots_kept: f64,
}

/// The quality scores of [`DatasetScores`] that carry a mean and a standard deviation, by name.
pub const QUALITY_SCORES: [&str; 7] = [
    "psnr",
    "ssim",
    "input_psnr",
    "ari",
    "fg_ari",
    "nv_ari",
    "nv_fg_ari",
];

fn mean(values: impl Iterator<Item = Option<f64>>) -> Option<f64> {
    mean_std(values).0
}

impl DatasetScores {
    /// Averages per-scene scores.
    pub fn from_scenes(rows: &[SceneScores]) -> DatasetScores {
        let stat = |f: fn(&SceneScores) -> Option<f64>| mean_std(rows.iter().map(f));
        let (psnr, psnr_std) = stat(|r| r.psnr);
        let (ssim, ssim_std) = stat(|r| r.ssim);
        let (input_psnr, input_psnr_std) = stat(|r| r.input_psnr);
        let (ari, ari_std) = stat(|r| r.ari);
        let (fg_ari, fg_ari_std) = stat(|r| r.fg_ari);
        let (nv_ari, nv_ari_std) = stat(|r| r.nv_ari);
        let (nv_fg_ari, nv_fg_ari_std) = stat(|r| r.nv_fg_ari);
        DatasetScores {
            scenes: rows.len(),
            psnr,
            psnr_std,
            ssim,
            ssim_std,
            input_psnr,
            input_psnr_std,
            ari,
            ari_std,
            fg_ari,
            fg_ari_std,
            nv_ari,
            nv_ari_std,
            nv_fg_ari,
            nv_fg_ari_std,
            fg_share: mean(rows.iter().map(|r| r.fg_share)),
            slots_used: mean(rows.iter().map(|r| Some(r.slots_used as f64))).unwrap_or(0.0),
            slots_kept: mean(rows.iter().map(|r| Some(r.slots_kept as f64))).unwrap_or(0.0),
        }
    }
}

/// Encodes view 0 of `scene` as the protocol does (slots placed with view 0's camera).
/// `opts` says how (its camera and source are set from the scene).
pub fn encode_scene(model: &Colf, scene: &SceneData, opts: &EncodeOptions) -> Result<Codes> {
    let Some(input) = scene.views.first() else {
        bail!("scene {} has no views", scene.name);
    };
    let opts = EncodeOptions {
        camera: Some(input.frame.clone()),
        source: scene.name.clone(),
        ..opts.clone()
    };
    encode_image(model, &input.image, &opts)
}

/// Encodes view 0 of `scene` and renders every view; returns the codes and the renders.
pub fn encode_and_render(
    model: &Colf,
    scene: &SceneData,
    opts: &EncodeOptions,
) -> Result<(Codes, Vec<FrameRender>)> {
    let codes = encode_scene(model, scene, opts)?;
    let prepared = PreparedScene::new(model, &codes, &scene.name)?;
    let renders = scene
        .views
        .iter()
        .map(|v| prepared.render_frame(model, &v.frame))
        .collect::<Result<Vec<_>>>()?;
    Ok((codes, renders))
}

/// Scores one scene from its renders (one per view, in order).
pub fn score_scene(scene: &SceneData, renders: &[FrameRender]) -> Result<SceneScores> {
    let mut row = SceneScores {
        scene: scene.name.clone(),
        ..Default::default()
    };
    let (mut psnrs, mut ssims) = (Vec::new(), Vec::new());
    let (mut nv_aris, mut nv_fg_aris) = (Vec::new(), Vec::new());
    let (mut fg_won, mut fg_total) = (0usize, 0usize);
    for (i, (view, render)) in scene.views.iter().zip(renders).enumerate() {
        let (w, h) = (view.image.w, view.image.h);
        if (render.width, render.height) != (w, h) {
            bail!(
                "{}: view {i} is {w}x{h} but was rendered at {}x{}",
                scene.name,
                render.width,
                render.height
            );
        }
        let p = psnr(&render.rgb, &view.image.data)?;
        let labels = render.labels();
        if i == 0 {
            row.input_psnr = Some(p);
            row.slots_used = {
                let mut used: Vec<u32> = labels.iter().copied().filter(|&l| l > 0).collect();
                used.sort_unstable();
                used.dedup();
                used.len()
            };
        } else {
            psnrs.push(p);
            if w >= 11 && h >= 11 {
                ssims.push(ssim(
                    &render.rgb,
                    &view.image.data,
                    w as usize,
                    h as usize,
                    3,
                )?);
            }
        }
        if let Some(mask) = &view.mask {
            let gt: Vec<u32> = mask.iter().map(|&m| m as u32).collect();
            for (l, g) in labels.iter().zip(&gt) {
                if *g > 0 {
                    fg_total += 1;
                    fg_won += (*l > 0) as usize;
                }
            }
            let full = ari(&labels, &gt)?;
            let fga = fg_ari(&labels, &gt)?;
            if i == 0 {
                row.ari = Some(full);
                row.fg_ari = fga;
            } else {
                nv_aris.push(full);
                nv_fg_aris.extend(fga);
            }
        }
    }
    let avg = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    row.psnr = avg(&psnrs);
    row.ssim = avg(&ssims);
    row.nv_ari = avg(&nv_aris);
    row.nv_fg_ari = avg(&nv_fg_aris);
    row.fg_share = (fg_total > 0).then(|| fg_won as f64 / fg_total as f64);
    Ok(row)
}

/// Evaluates the first `max_scenes` scenes of `data` (all when `None`); `on_scene` sees each
/// row as it is done (progress, per-scene output).
pub fn evaluate(
    model: &Colf,
    data: &Dataset,
    max_scenes: Option<usize>,
    opts: &EncodeOptions,
    mut on_scene: impl FnMut(usize, &SceneScores, &[FrameRender]),
) -> Result<(DatasetScores, Vec<SceneScores>)> {
    let n = max_scenes.map_or(data.len(), |m| m.min(data.len()));
    let mut rows = Vec::with_capacity(n);
    for i in 0..n {
        let scene = data.load(i)?;
        let (codes, renders) = encode_and_render(model, &scene, opts)
            .with_context(|| format!("scene {}", scene.name))?;
        let mut row = score_scene(&scene, &renders)?;
        row.slots_kept = codes.slots.len();
        on_scene(i, &row, &renders);
        rows.push(row);
    }
    Ok((DatasetScores::from_scenes(&rows), rows))
}
