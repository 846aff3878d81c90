//! The uORF evaluation protocol on a dataset: per scene, view 0 is encoded (slots placed with
//! view 0's camera), every view is rendered; ARI and FG-ARI are taken on view 0, PSNR, SSIM,
//! NV-ARI and NV-FG-ARI averaged over the other views; then the mean (and the standard
//! deviation) over scenes.
//!
//! With several input views (`colf-eval --input-views 0,1,2`), those views are encoded
//! together (`encode::multiview`); ARI, FG-ARI and the input PSNR are averaged over them, the
//! novel-view scores over the rest, and the objects that two or more input views show are
//! checked to be drawn by exactly one slot ([`SceneScores::objects_one_slot`]).
//!
//! NV-ARI is uORF's (`models/uorf_eval_model.py`), as every published CLEVR-567 table uses it:
//! the adjusted Rand index of the full label maps of a novel view, background included. The
//! FG-ARI of the novel views (ground-truth object pixels only) is a different number and is
//! reported as `nv_fg_ari`.

use crate::codes::Codes;
use crate::dataset::{Dataset, SceneData};
use crate::encode::multiview::{encode_views, ViewInput};
use crate::encode::refine::{refine_slots, RefineOptions};
use crate::encode::{EncodeOptions, InputView};
use crate::metrics::{ari, fg_ari, mean_std, psnr, region_psnr, ssim};
use crate::model::Colf;
use crate::render::output::FrameRender;
use crate::render::PreparedScene;
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

pub mod journal;

/// Scores of one scene. `None` where a score is undefined (no masks, or no foreground pixel).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct SceneScores {
    pub scene: String,
    /// Mean PSNR of the novel views (dB).
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    /// PSNR of the novel views over their ground-truth object pixels, and over the rest
    /// (floor, walls, sky), each averaged over the views where its region has pixels.
    pub object_psnr: Option<f64>,
    pub background_psnr: Option<f64>,
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
    /// With several input views: the ground-truth objects that at least two of them show
    /// (at least [`MIN_OBJECT_PIXELS`] pixels each).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub objects_seen_twice: Option<usize>,
    /// …and of those, the objects drawn by exactly one slot: across the input views that show
    /// the object, one and the same slot, and no other, wins at least [`SLOT_SHARE`] of its
    /// pixels (an object drawn by two slots, or by the background alone, fails).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub objects_one_slot: Option<usize>,
    /// …and the objects no slot draws (the background wins more than three quarters of their
    /// pixels in every input view that shows them); the rest of the failures are split or
    /// shared between slots.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub objects_no_slot: Option<usize>,
    /// How the FG-ARI splits between views with one object and the rest ([`LoneObjects`]);
    /// left out of the JSON where no scored view shows a lone object.
    #[serde(flatten, skip_serializing_if = "LoneObjects::is_empty")]
    pub lone: LoneObjects,
}

/// FG-ARI split by how many ground-truth objects a view shows. With one object the FG-ARI is
/// all or nothing: 1 when every pixel of it has the same predicted label, 0 as soon as two
/// labels share it, however few pixels the second holds (a street's context view in front of a
/// row with one car). So a data set with such views also gets the FG-ARI of its views with two
/// objects or more, and the count of its lone-object views and of those drawn whole.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LoneObjects {
    /// FG-ARI averaged over the input views that show two objects or more.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fg_ari_multi: Option<f64>,
    /// Input views that show exactly one object…
    pub lone_object_views: usize,
    /// …and of those, the views whose object one label wins whole (FG-ARI 1; the label may be
    /// the background's, as FG-ARI counts it).
    pub lone_object_whole: usize,
    /// The same for the novel views.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nv_fg_ari_multi: Option<f64>,
    pub nv_lone_object_views: usize,
    pub nv_lone_object_whole: usize,
}

impl LoneObjects {
    /// Whether no scored view showed a lone object (then the split says nothing new).
    pub fn is_empty(&self) -> bool {
        self.lone_object_views == 0 && self.nv_lone_object_views == 0
    }
}

/// Of one view's ground-truth object pixels: `None` without any, else whether the view shows
/// a single object and, if so, whether one predicted label wins all of its pixels.
fn lone_object(labels: &[u32], gt: &[u32]) -> Option<(bool, bool)> {
    let mut object_pixels = labels.iter().zip(gt).filter(|(_, &g)| g > 0);
    let (&first_label, &first_object) = object_pixels.next()?;
    let (mut one_object, mut one_label) = (true, true);
    for (&l, &g) in object_pixels {
        one_object &= g == first_object;
        one_label &= l == first_label;
    }
    Some((one_object, one_object && one_label))
}

/// Which views of a scene are encoded and which are scored as novel views.
#[derive(Clone, Debug, PartialEq)]
pub struct Protocol {
    /// Encoded together (`[0]`: uORF's protocol).
    pub inputs: Vec<usize>,
    /// Scored as novel views (None: every view that is not an input).
    pub novel: Option<Vec<usize>>,
}

impl Default for Protocol {
    fn default() -> Self {
        Protocol {
            inputs: vec![0],
            novel: None,
        }
    }
}

impl Protocol {
    /// Whether view `v` is scored as a novel view.
    fn is_novel(&self, v: usize) -> bool {
        match &self.novel {
            Some(novel) => novel.contains(&v),
            None => !self.inputs.contains(&v),
        }
    }
}

/// An object shows in a view when its mask has at least this many pixels there.
pub const MIN_OBJECT_PIXELS: usize = 10;

/// A slot draws an object in a view when it wins at least this share of the object's pixels.
pub const SLOT_SHARE: f64 = 0.25;

/// Means over scenes (each over the scenes where the score is defined), and for the quality
/// scores the population standard deviation over the same scenes (`*_std`).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct DatasetScores {
    pub scenes: usize,
    pub psnr: Option<f64>,
    pub psnr_std: Option<f64>,
    pub ssim: Option<f64>,
    pub ssim_std: Option<f64>,
    pub object_psnr: Option<f64>,
    pub object_psnr_std: Option<f64>,
    pub background_psnr: Option<f64>,
    pub background_psnr_std: Option<f64>,
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
    /// With several input views: the share of the objects seen by two or more of them that
    /// exactly one slot draws (over all scenes' objects), and how many such objects there were.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub one_slot_share: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub objects_seen_twice: Option<usize>,
    /// …and the share of them that no slot draws (left to the background).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub no_slot_share: Option<f64>,
    /// Where some scored views show a lone object ([`LoneObjects`]): the FG-ARI of the views
    /// with two objects or more (means over scenes, as `fg_ari`), the lone-object views counted
    /// over all scenes and the share of them drawn whole.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fg_ari_multi: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lone_object_views: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lone_object_whole_share: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nv_fg_ari_multi: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nv_lone_object_views: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nv_lone_object_whole_share: Option<f64>,
}

/// The quality scores of [`DatasetScores`] that carry a mean and a standard deviation, by name.
pub const QUALITY_SCORES: [&str; 9] = [
    "psnr",
    "ssim",
    "object_psnr",
    "background_psnr",
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
        let (object_psnr, object_psnr_std) = stat(|r| r.object_psnr);
        let (background_psnr, background_psnr_std) = stat(|r| r.background_psnr);
        let (input_psnr, input_psnr_std) = stat(|r| r.input_psnr);
        let (ari, ari_std) = stat(|r| r.ari);
        let (fg_ari, fg_ari_std) = stat(|r| r.fg_ari);
        let (nv_ari, nv_ari_std) = stat(|r| r.nv_ari);
        let (nv_fg_ari, nv_fg_ari_std) = stat(|r| r.nv_fg_ari);
        let objects_seen_twice = rows
            .iter()
            .filter_map(|r| r.objects_seen_twice)
            .reduce(|a, b| a + b);
        let share = |count: fn(&SceneScores) -> Option<usize>| {
            let counted: usize = rows.iter().filter_map(count).sum();
            objects_seen_twice
                .filter(|&n| n > 0)
                .map(|n| counted as f64 / n as f64)
        };
        let one_slot_share = share(|r| r.objects_one_slot);
        let no_slot_share = share(|r| r.objects_no_slot);
        let any_lone = rows.iter().any(|r| !r.lone.is_empty());
        let lone_sum =
            |f: fn(&LoneObjects) -> usize| rows.iter().map(|r| f(&r.lone)).sum::<usize>();
        let (lone_views, nv_lone_views) = (
            lone_sum(|l| l.lone_object_views),
            lone_sum(|l| l.nv_lone_object_views),
        );
        let whole_share =
            |whole: usize, views: usize| (views > 0).then(|| whole as f64 / views as f64);
        DatasetScores {
            scenes: rows.len(),
            psnr,
            psnr_std,
            ssim,
            ssim_std,
            object_psnr,
            object_psnr_std,
            background_psnr,
            background_psnr_std,
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
            one_slot_share,
            objects_seen_twice,
            no_slot_share,
            fg_ari_multi: any_lone
                .then(|| mean(rows.iter().map(|r| r.lone.fg_ari_multi)))
                .flatten(),
            lone_object_views: any_lone.then_some(lone_views),
            lone_object_whole_share: whole_share(lone_sum(|l| l.lone_object_whole), lone_views),
            nv_fg_ari_multi: any_lone
                .then(|| mean(rows.iter().map(|r| r.lone.nv_fg_ari_multi)))
                .flatten(),
            nv_lone_object_views: any_lone.then_some(nv_lone_views),
            nv_lone_object_whole_share: whole_share(
                lone_sum(|l| l.nv_lone_object_whole),
                nv_lone_views,
            ),
        }
    }
}

/// Encodes the views `inputs` of `scene` (view 0 alone: the protocol's encoding, slots placed
/// with view 0's camera). `opts` says how (cameras and sources are set from the scene).
pub fn encode_scene(
    model: &Colf,
    scene: &SceneData,
    inputs: &[usize],
    opts: &EncodeOptions,
) -> Result<Codes> {
    check_inputs(scene, inputs)?;
    let views: Vec<ViewInput> = inputs
        .iter()
        .map(|&v| ViewInput {
            image: &scene.views[v].image,
            camera: scene.views[v].frame.clone(),
            // One view keeps the protocol's source name (the scene's), several name the view.
            source: if inputs.len() == 1 {
                scene.name.clone()
            } else {
                format!("{}/view{v}", scene.name)
            },
        })
        .collect();
    Ok(encode_views(model, &views, opts)?.0)
}

/// The bound on what any encoding could do (`examples/multiview_fit`, `capacity_fit`): the
/// latents and frame origins of a start refined on the first `views` views of `scene` for
/// `steps` steps (the `colf-encode --refine` settings otherwise). The start is view 0 encoded in
/// one pass with the model's default slot count, or with `start`, the first `views` views
/// encoded together that way (a multi-view encoding already fitted to them: the fit is not
/// convex, and a start that missed an object keeps missing it).
pub fn fit_latents_to_views(
    model: &Colf,
    scene: &SceneData,
    views: usize,
    steps: usize,
    start: Option<&EncodeOptions>,
) -> Result<Codes> {
    if scene.views.len() < views {
        bail!(
            "{}: {} views, fewer than the {views} to fit",
            scene.name,
            scene.views.len()
        );
    }
    let mut codes = match start {
        None => {
            let one_pass = EncodeOptions::one_pass(model.config().default_slots);
            encode_scene(model, scene, &[0], &one_pass)?
        }
        Some(opts) => encode_scene(model, scene, &(0..views).collect::<Vec<_>>(), opts)?,
    };
    let inputs: Vec<InputView> = scene.views[..views]
        .iter()
        .map(|v| InputView::new(&v.frame, &v.image))
        .collect();
    let inputs: Vec<&InputView> = inputs.iter().collect();
    let refine = RefineOptions {
        steps,
        ..RefineOptions::default()
    };
    refine_slots(
        model,
        &mut codes.slots,
        &mut codes.background,
        &inputs,
        &refine,
    )?;
    Ok(codes)
}

/// Why `inputs` cannot name the input views of any scene (none, or one twice), if so.
pub fn input_views_error(inputs: &[usize]) -> Option<String> {
    if inputs.is_empty() {
        return Some("no input view to encode".into());
    }
    (1..inputs.len())
        .find(|&i| inputs[..i].contains(&inputs[i]))
        .map(|i| format!("input view {} is named twice", inputs[i]))
}

/// Refuses input views a scene does not have, or none, or one twice.
fn check_inputs(scene: &SceneData, inputs: &[usize]) -> Result<()> {
    if let Some(error) = input_views_error(inputs) {
        bail!(error);
    }
    if let Some(&v) = inputs.iter().find(|&&v| v >= scene.views.len()) {
        bail!(
            "scene {} has {} views; there is no input view {v}",
            scene.name,
            scene.views.len()
        );
    }
    Ok(())
}

/// Encodes the views `inputs` of `scene` and renders every view; returns the codes and the
/// renders.
pub fn encode_and_render(
    model: &Colf,
    scene: &SceneData,
    inputs: &[usize],
    opts: &EncodeOptions,
) -> Result<(Codes, Vec<FrameRender>)> {
    let codes = encode_scene(model, scene, inputs, opts)?;
    let prepared = PreparedScene::new(model, &codes, &scene.name)?;
    let renders = scene
        .views
        .iter()
        .map(|v| prepared.render_frame(model, &v.frame))
        .collect::<Result<Vec<_>>>()?;
    Ok((codes, renders))
}

/// Scores one scene from its renders (one per view, in order), as `protocol` says.
pub fn score_scene(
    scene: &SceneData,
    renders: &[FrameRender],
    protocol: &Protocol,
) -> Result<SceneScores> {
    let inputs = &protocol.inputs;
    if let Some(&v) = protocol
        .novel
        .iter()
        .flatten()
        .find(|&&v| v >= scene.views.len())
    {
        bail!(
            "scene {} has {} views; there is no novel view {v}",
            scene.name,
            scene.views.len()
        );
    }
    let mut row = SceneScores {
        scene: scene.name.clone(),
        ..Default::default()
    };
    let (mut psnrs, mut ssims) = (Vec::new(), Vec::new());
    let (mut object_psnrs, mut background_psnrs) = (Vec::new(), Vec::new());
    let (mut nv_aris, mut nv_fg_aris) = (Vec::new(), Vec::new());
    let (mut input_psnrs, mut input_aris, mut input_fg_aris) = (Vec::new(), Vec::new(), Vec::new());
    let (mut multi_fg_aris, mut nv_multi_fg_aris) = (Vec::new(), Vec::new());
    let mut used: Vec<u32> = Vec::new();
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
        let input = inputs.contains(&i);
        let novel = protocol.is_novel(i);
        if input {
            input_psnrs.push(p);
            used.extend(labels.iter().copied().filter(|&l| l > 0));
        }
        if novel {
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
            let lone = lone_object(&labels, &gt);
            let multi = fga.filter(|_| lone.is_some_and(|(one, _)| !one));
            let (lone_view, lone_whole) = match lone {
                Some((true, whole)) => (1, whole as usize),
                _ => (0, 0),
            };
            if input {
                input_aris.push(full);
                input_fg_aris.extend(fga);
                multi_fg_aris.extend(multi);
                row.lone.lone_object_views += lone_view;
                row.lone.lone_object_whole += lone_whole;
            }
            if novel {
                let inside: Vec<bool> = mask.iter().map(|&m| m != 0).collect();
                let (object, background) = region_psnr(&render.rgb, &view.image.data, &inside)?;
                object_psnrs.extend(object);
                background_psnrs.extend(background);
                nv_aris.push(full);
                nv_fg_aris.extend(fga);
                nv_multi_fg_aris.extend(multi);
                row.lone.nv_lone_object_views += lone_view;
                row.lone.nv_lone_object_whole += lone_whole;
            }
        }
    }
    used.sort_unstable();
    used.dedup();
    row.slots_used = used.len();
    let avg = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    row.input_psnr = avg(&input_psnrs);
    row.ari = avg(&input_aris);
    row.fg_ari = avg(&input_fg_aris);
    row.psnr = avg(&psnrs);
    row.ssim = avg(&ssims);
    row.object_psnr = avg(&object_psnrs);
    row.background_psnr = avg(&background_psnrs);
    row.nv_ari = avg(&nv_aris);
    row.nv_fg_ari = avg(&nv_fg_aris);
    row.lone.fg_ari_multi = avg(&multi_fg_aris);
    row.lone.nv_fg_ari_multi = avg(&nv_multi_fg_aris);
    row.fg_share = (fg_total > 0).then(|| fg_won as f64 / fg_total as f64);
    if inputs.len() > 1 {
        if let Some(objects) = objects_one_slot(scene, renders, inputs) {
            row.objects_seen_twice = Some(objects.seen_twice);
            row.objects_one_slot = Some(objects.one_slot);
            row.objects_no_slot = Some(objects.no_slot);
        }
    }
    Ok(row)
}

/// Counts of ground-truth objects at least two input views show.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct ObjectSlots {
    seen_twice: usize,
    /// Drawn by exactly one slot ([`SceneScores::objects_one_slot`]).
    one_slot: usize,
    /// Drawn by no slot.
    no_slot: usize,
}

/// Of the ground-truth objects at least two input views show, how many, how many exactly one
/// slot draws (see [`SceneScores::objects_one_slot`]) and how many none; None when an input
/// view has no mask or the masks' ids are local to each view.
fn objects_one_slot(
    scene: &SceneData,
    renders: &[FrameRender],
    inputs: &[usize],
) -> Option<ObjectSlots> {
    use std::collections::{BTreeMap, BTreeSet};
    if scene.view_local_ids {
        // Proposal ids name no object across views.
        return None;
    }
    // Per object: the input views that show it, and the slots that draw it in any of them.
    let mut shown: BTreeMap<u32, usize> = BTreeMap::new();
    let mut drawn_by: BTreeMap<u32, BTreeSet<u32>> = BTreeMap::new();
    for &v in inputs {
        let mask = scene.views[v].mask.as_ref()?;
        let labels = renders[v].labels();
        let mut pixels: BTreeMap<u32, BTreeMap<u32, usize>> = BTreeMap::new();
        for (&g, &l) in mask.iter().zip(&labels) {
            if g > 0 {
                *pixels.entry(g as u32).or_default().entry(l).or_default() += 1;
            }
        }
        for (object, by_label) in pixels {
            let total: usize = by_label.values().sum();
            if total < MIN_OBJECT_PIXELS {
                continue;
            }
            *shown.entry(object).or_default() += 1;
            let slots = drawn_by.entry(object).or_default();
            for (label, count) in by_label {
                if label > 0 && count as f64 >= SLOT_SHARE * total as f64 {
                    slots.insert(label);
                }
            }
        }
    }
    let twice: Vec<u32> = shown
        .iter()
        .filter(|&(_, &views)| views >= 2)
        .map(|(&o, _)| o)
        .collect();
    let drawn_by_n = |n: usize| twice.iter().filter(|o| drawn_by[o].len() == n).count();
    Some(ObjectSlots {
        seen_twice: twice.len(),
        one_slot: drawn_by_n(1),
        no_slot: drawn_by_n(0),
    })
}

/// Evaluates the first `max_scenes` scenes of `data` (all when `None`), encoding and scoring
/// the views `protocol` names; `on_scene` sees each row as it is done (progress,
/// per-scene output, a journal); its error stops the evaluation at once. `done` holds the rows
/// of the first scenes, scored before with the same model and options (a journal's,
/// [`journal`]): those scenes are not scored again.
pub fn evaluate(
    model: &Colf,
    data: &Dataset,
    max_scenes: Option<usize>,
    protocol: &Protocol,
    opts: &EncodeOptions,
    done: Vec<SceneScores>,
    mut on_scene: impl FnMut(usize, &SceneScores, &[FrameRender]) -> Result<()>,
) -> Result<(DatasetScores, Vec<SceneScores>)> {
    let n = max_scenes.map_or(data.len(), |m| m.min(data.len()));
    if done.len() > n {
        bail!(
            "{} scenes were scored before, but there are only {n} to score",
            done.len()
        );
    }
    let mut rows = done;
    rows.reserve(n - rows.len());
    for i in rows.len()..n {
        let scene = data.load(i)?;
        let (codes, renders) = encode_and_render(model, &scene, &protocol.inputs, opts)
            .with_context(|| format!("scene {}", scene.name))?;
        let mut row = score_scene(&scene, &renders, protocol)?;
        row.slots_kept = codes.slots.len();
        on_scene(i, &row, &renders)?;
        rows.push(row);
    }
    Ok((DatasetScores::from_scenes(&rows), rows))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::View;

    /// A 4-pixel view whose mask is `mask`, and a render whose labels are `labels`.
    fn view_and_render(mask: [u8; 4], labels: [usize; 4]) -> (View, FrameRender) {
        let frame = crate::encode::default_camera(2, 2);
        let view = View {
            path: "v.png".into(),
            image: crate::image_io::RgbImage32 {
                w: 2,
                h: 2,
                data: vec![0.5; 12],
            },
            mask: Some(mask.to_vec()),
            frame,
        };
        let fields = 3;
        let mut weights = vec![0f32; 4 * fields];
        for (p, &l) in labels.iter().enumerate() {
            weights[p * fields + l] = 1.0;
        }
        let render = FrameRender {
            width: 2,
            height: 2,
            num_slots: fields - 1,
            rgb: vec![0.5; 12],
            weights,
            ordering: vec![0.0; 4 * fields],
        };
        (view, render)
    }

    #[test]
    fn the_bound_starts_from_view_0_or_from_the_views_encoded_together() {
        let model = Colf::init(&crate::model::Config::small(), 1).unwrap();
        let view = |shade: f32| View {
            path: "v.png".into(),
            image: crate::image_io::RgbImage32 {
                w: 32,
                h: 32,
                data: (0..32 * 32 * 3)
                    .map(|i| shade * (i % 7) as f32 / 7.0)
                    .collect(),
            },
            mask: None,
            frame: crate::encode::default_camera(32, 32),
        };
        let scene = SceneData {
            name: "s".into(),
            views: vec![view(0.4), view(0.8)],
            view_local_ids: false,
        };
        let one_pass = EncodeOptions::one_pass(model.config().default_slots);
        // No steps: the fit is its start.
        let from_view_0 = fit_latents_to_views(&model, &scene, 2, 0, None).unwrap();
        assert_eq!(
            from_view_0,
            encode_scene(&model, &scene, &[0], &one_pass).unwrap()
        );
        let together = fit_latents_to_views(&model, &scene, 2, 0, Some(&one_pass)).unwrap();
        assert_eq!(
            together,
            encode_scene(&model, &scene, &[0, 1], &one_pass).unwrap()
        );
        assert_ne!(together, from_view_0);
        // Steps move the start; more views than the scene has are refused.
        let fitted = fit_latents_to_views(&model, &scene, 2, 2, Some(&one_pass)).unwrap();
        assert_ne!(fitted, together);
        assert!(fit_latents_to_views(&model, &scene, 3, 0, None).is_err());
    }

    #[test]
    fn lone_object_views_are_counted_apart_from_the_fg_ari_of_the_others() {
        // View 0 (input): two objects, object 2 split between slot 2 and the background.
        // View 1 (novel): one object, one pixel of it won by the background: FG-ARI 0.
        // View 2 (novel): one object, drawn whole by slot 1: FG-ARI 1.
        let (a, ra) = view_and_render([1, 1, 2, 2], [1, 1, 2, 0]);
        let (b, rb) = view_and_render([0, 1, 1, 1], [0, 1, 1, 0]);
        let (c, rc) = view_and_render([1, 1, 0, 0], [1, 1, 0, 2]);
        let scene = SceneData {
            name: "s".into(),
            views: vec![a, b, c],
            view_local_ids: false,
        };
        let row = score_scene(&scene, &[ra, rb, rc], &Protocol::default()).unwrap();
        let view_0 = fg_ari(&[1, 1, 2, 0], &[1, 1, 2, 2]).unwrap();
        assert_eq!(row.fg_ari, view_0);
        assert_eq!(row.nv_fg_ari, Some(0.5));
        let expected = LoneObjects {
            fg_ari_multi: view_0,
            lone_object_views: 0,
            lone_object_whole: 0,
            nv_fg_ari_multi: None,
            nv_lone_object_views: 2,
            nv_lone_object_whole: 1,
        };
        assert_eq!(row.lone, expected);
        let json = serde_json::to_value(&row).unwrap();
        assert_eq!(json["nv_lone_object_views"], 2);
        assert!(json.get("nv_fg_ari_multi").is_none());

        let scores = DatasetScores::from_scenes(&[row.clone(), row.clone()]);
        assert_eq!(scores.fg_ari_multi, view_0);
        assert_eq!(scores.lone_object_views, Some(0));
        assert_eq!(scores.lone_object_whole_share, None);
        assert_eq!(scores.nv_lone_object_views, Some(4));
        assert_eq!(scores.nv_lone_object_whole_share, Some(0.5));

        // Without lone objects nothing is added, to the scene's JSON or the data set's.
        let (d, rd) = view_and_render([1, 1, 2, 2], [1, 1, 2, 2]);
        let plain = SceneData {
            views: vec![d.clone(), d],
            ..scene
        };
        let row = score_scene(&plain, &[rd.clone(), rd], &Protocol::default()).unwrap();
        assert!(row.lone.is_empty());
        let json = serde_json::to_value(&row).unwrap();
        assert!(json.get("lone_object_views").is_none() && json.get("fg_ari_multi").is_none());
        let scores = DatasetScores::from_scenes(&[row]);
        let json = serde_json::to_value(&scores).unwrap();
        assert!(json.get("lone_object_views").is_none() && json.get("fg_ari_multi").is_none());
    }

    #[test]
    fn an_object_counts_once_when_one_slot_draws_it_in_every_view() {
        // Object 1 fills pixels 0–1 and object 2 pixels 2–3 of both views. View a: slot 1
        // draws object 1, slot 2 object 2. View b: slot 1 draws object 1 again, but object 2
        // is split between slot 1 and slot 2 (two slots draw it).
        let (a, ra) = view_and_render([1, 1, 2, 2], [1, 1, 2, 2]);
        let (b, rb) = view_and_render([1, 1, 2, 2], [1, 1, 1, 2]);
        let scene = SceneData {
            name: "s".into(),
            views: vec![a, b],
            view_local_ids: false,
        };
        let renders = [ra, rb];
        // MIN_OBJECT_PIXELS is 10: a 4-pixel view shows no object.
        let counts = |seen_twice, one_slot, no_slot| {
            Some(ObjectSlots {
                seen_twice,
                one_slot,
                no_slot,
            })
        };
        assert_eq!(objects_one_slot(&scene, &renders, &[0, 1]), counts(0, 0, 0));
        let big = |v: &View, r: &FrameRender| {
            let mut v = v.clone();
            let mut r = r.clone();
            v.mask = Some(v.mask.unwrap().repeat(MIN_OBJECT_PIXELS));
            r.weights = r.weights.repeat(MIN_OBJECT_PIXELS);
            (v, r)
        };
        let (a, ra) = big(&scene.views[0], &renders[0]);
        let (b, rb) = big(&scene.views[1], &renders[1]);
        let scene = SceneData {
            views: vec![a, b],
            ..scene
        };
        let renders = [ra, rb];
        assert_eq!(objects_one_slot(&scene, &renders, &[0, 1]), counts(2, 1, 0));
        // One input view: no object is seen twice.
        assert_eq!(objects_one_slot(&scene, &renders, &[0]), counts(0, 0, 0));
        // The background draws object 2 in both views: no slot draws it.
        let mut unseen = renders.clone();
        for r in &mut unseen {
            let fields = r.num_slots + 1;
            for (p, &g) in scene.views[0].mask.as_ref().unwrap().iter().enumerate() {
                if g == 2 {
                    for f in 0..fields {
                        r.weights[p * fields + f] = if f == 0 { 1.0 } else { 0.0 };
                    }
                }
            }
        }
        assert_eq!(objects_one_slot(&scene, &unseen, &[0, 1]), counts(2, 1, 1));
        let local = SceneData {
            view_local_ids: true,
            ..scene
        };
        assert_eq!(objects_one_slot(&local, &renders, &[0, 1]), None);
    }
}
