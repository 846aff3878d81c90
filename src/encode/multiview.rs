//! Several views in, one scene out: encoding a scene from images taken by several cameras.
//!
//! Each view is encoded on its own ([`super::best_of_tries`], then the slots its own view does
//! not need dropped), so every view proposes slots, in world frames, for the objects it sees.
//! An object seen by two views then has two slots; keeping both would draw it twice and break
//! every edit (moving one copy leaves the other). So the views' slots are **matched**: view by
//! view, each slot set is rendered into every view taken so far, and two slots that cover the
//! same pixels there (intersection over union of their label maps, summed over the views where
//! both draw, at least [`MATCH_IOU`]) are one object, and so is a newcomer lying mostly inside
//! one kept slot (a piece of an object its view split); the slot already kept stays and the
//! newcomer goes, unless the newcomer draws in more of the views (see [`Matching`]). A slot
//! no earlier slot matches is an object only this view saw, and joins. With
//! `triangulate_steps`, from the third view on the slots kept so far are first refined on the
//! views already taken: each was placed at one view's guess of its depth, and the views
//! together move it to where they agree before the next view's slots are compared with it. The background is the
//! first view's. Then the default encoding's refinement runs on all views at once (its rays
//! per step are per view: V views, V times the pixels a step). With `agreed_slots`, what the
//! views then agree the slots still miss gets new slots, refined again with the rest
//! ([`super::residual`]), the step undone if the input views are then drawn worse (an added
//! slot can pull the refinement off them). Last, the slots no view needs are dropped (the
//! redundancy budget on the mean error over the views).
//!
//! Matching by what the slots draw, not by where their frames sit: a slot's frame origin is
//! only a guess of the object's position along its ray (`model::frames`), while its rendered
//! pixels in a shared view are what an edit would move.

use super::redundant::drop_redundant_slots;
use super::refine::{self, RefineReport};
use super::view::InputView;
use super::{best_of_tries, latents_and_frames, EncodeOptions};
use crate::camera::Frame;
use crate::codes::{Codes, Slot};
use crate::image_io::RgbImage32;
use crate::model::Colf;
use crate::render::fast::FastRenderer;
use anyhow::{bail, Result};

/// Two slots from different views are one object when their label maps overlap this much
/// (intersection over union over the views compared).
pub const MATCH_IOU: f64 = 0.2;

/// A newcomer slot is a fragment of a kept slot's object when at least this share of its pixels
/// lie inside that slot's, in every view where it draws [`FRAGMENT_PIXELS`] or more.
pub const FRAGMENT_SHARE: f64 = 0.6;
pub const FRAGMENT_PIXELS: usize = 4;

/// With several views and no explicit step count, the refinement takes this many times the
/// model's default steps: the single-view count stops before the input view is overfitted,
/// and several views constrain the latents more. On the first 20 held-out analytic 128² scenes,
/// three views → view 3 scored 28.28 dB with the model's 50 steps and 28.62 dB with 100
/// (docs/eval.md, "Several input views").
pub const MULTI_VIEW_REFINE_FACTOR: usize = 2;

/// One image of the scene, its camera, and the name its slots' sources carry.
pub struct ViewInput<'a> {
    pub image: &'a RgbImage32,
    pub camera: Frame,
    pub source: String,
}

/// What a multi-view encoding did besides its codes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MultiViewReport {
    /// Slots each view proposed (after its own redundancy drop), in view order.
    pub proposed: Vec<usize>,
    /// Slots of later views found to draw an object an earlier view's slot already drew.
    pub matched: usize,
    /// Slots added where the views agreed on an object no slot drew (before the last drop).
    pub agreed: usize,
    /// Whether the slots were put back as they were before the agreed ones were added, the
    /// refinement that followed having drawn the input views worse.
    pub agreed_undone: bool,
    /// Refinement steps taken to triangulate the kept slots before matching
    /// ([`EncodeOptions::triangulate_steps`]).
    pub triangulated: usize,
    /// The joint refinement, if it ran.
    pub refine: Option<RefineReport>,
}

/// Encodes one scene from `inputs` (one or more views with their cameras). One view is
/// exactly [`super::encode_image_report`] with that camera and source (same bytes); `opts`'
/// own `camera` and `source` are not read.
pub fn encode_views(
    model: &Colf,
    inputs: &[ViewInput],
    opts: &EncodeOptions,
) -> Result<(Codes, MultiViewReport)> {
    opts.check()?;
    refine::check_mask(model, &opts.refine)?;
    let single = |input: &ViewInput| EncodeOptions {
        camera: Some(input.camera.clone()),
        source: input.source.clone(),
        ..opts.clone()
    };
    match inputs {
        [] => bail!("no view to encode"),
        [input] => {
            let (codes, refine) = super::encode_image_report(model, input.image, &single(input))?;
            let report = MultiViewReport {
                proposed: vec![codes.slots.len()],
                matched: 0,
                agreed: 0,
                agreed_undone: false,
                triangulated: 0,
                refine,
            };
            return Ok((codes, report));
        }
        _ => {}
    }
    let views: Vec<InputView> = inputs
        .iter()
        .map(|input| InputView::new(&input.camera, input.image))
        .collect();
    let mut report = MultiViewReport::default();
    // 1. Each view's own encoding: the best of its tries, less the slots it does not need.
    let mut proposals = Vec::with_capacity(inputs.len());
    for (input, view) in inputs.iter().zip(&views) {
        // Judged with the model's own slots and shadows: the matching below compares them.
        let (slots, background) = best_of_tries(model, view, &single(input), None)?;
        let slots =
            drop_redundant_slots(model, slots, &background, &[view], opts.redundant_mse, None)?;
        report.proposed.push(slots.len());
        proposals.push((slots, background));
    }
    // `rays` is per view: each view gets the pixels a step of its own encoding gives it.
    let joint = |steps: usize, views: usize| refine::RefineOptions {
        steps,
        rays: opts.refine.rays.saturating_mul(views),
        ..opts.refine
    };
    // 2. One slot per object: later views' slots matched against those kept so far.
    let mut proposals = proposals.into_iter();
    let (mut slots, mut background) = proposals.next().expect("two views or more");
    for (i, (newcomers, newcomers_background)) in proposals.enumerate() {
        let seen = &views[..i + 2];
        if opts.triangulate_steps > 0 && i > 0 {
            // Triangulation: the kept slots came from two views or more, each placed at its
            // own view's guess of the depth; refined on those views together, they move to
            // where the views agree, so the newcomers are matched against slots drawn from
            // the right place.
            let taken: Vec<&InputView> = views[..i + 1].iter().collect();
            let steps = joint(opts.triangulate_steps, taken.len());
            report.triangulated +=
                refine::refine_slots(model, &mut slots, &mut background, &taken, &steps)?.steps;
        }
        let matched = match_slots(
            model,
            (&slots, &background),
            (&newcomers, &newcomers_background),
            seen,
        )?;
        report.matched += matched.of.iter().filter(|m| m.is_some()).count();
        for ((newcomer, of), takes_over) in newcomers
            .into_iter()
            .zip(matched.of)
            .zip(matched.takes_over)
        {
            match of {
                None => slots.push(newcomer),
                Some(kept) if takes_over => slots[kept] = newcomer,
                Some(_) => {}
            }
        }
    }
    // 3. All views at once: refinement.
    let all: Vec<&InputView> = views.iter().collect();
    if opts.refine.steps > 0 {
        report.refine = Some(refine::refine_slots(
            model,
            &mut slots,
            &mut background,
            &all,
            &joint(opts.refine.steps, all.len()),
        )?);
    }
    // 4. What the views agree on and no slot draws: new slots, then all refined again.
    if opts.agreed_slots > 0 {
        let before = (slots.clone(), background.clone());
        let first_added = slots.len();
        let added = super::residual::add_agreed_slots(
            model,
            &mut slots,
            &background,
            &all,
            opts.agreed_slots,
        )?;
        report.agreed = added;
        if added > 0 && opts.refine.steps > 0 {
            let steps = joint(opts.refine.steps.div_ceil(2), all.len());
            refine::refine_slots(model, &mut slots, &mut background, &all, &steps)?;
        }
        slots = super::residual::keep_agreed(model, slots, &background, &all, first_added)?;
        // The added slots start from another slot's latent and can pull the refinement off
        // the views (a slot that drew an object gives it up, and the drop below removes it):
        // the slots after this step stay only if they draw the input views no worse.
        if added > 0 {
            ((slots, background), report.agreed_undone) =
                no_worse_than(model, (slots, background), before, &all)?;
        }
    }
    // 5. The slots no view needs dropped.
    let slots = drop_redundant_slots(model, slots, &background, &all, opts.redundant_mse, None)?;
    let codes = Codes {
        slots,
        background,
        model: model.identity()?,
    };
    Ok((codes, report))
}

/// A scene's slots and background, as an encoding holds them before writing its codes.
type SlotSet = (Vec<Slot>, Vec<f32>);

/// `candidate` (slots and background) unless it draws `views` worse than `before` (the mean
/// squared error of [`views_mse`]), then `before`; and whether `before` was taken.
fn no_worse_than(
    model: &Colf,
    candidate: SlotSet,
    before: SlotSet,
    views: &[&InputView],
) -> Result<(SlotSet, bool)> {
    let worse = views_mse(model, &candidate.0, &candidate.1, views)?
        > views_mse(model, &before.0, &before.1, views)?;
    Ok(if worse {
        (before, true)
    } else {
        (candidate, false)
    })
}

/// The mean over `views` of the squared colour error of `slots` and `background` on each
/// view's compared pixels.
fn views_mse(
    model: &Colf,
    slots: &[Slot],
    background: &[f32],
    views: &[&InputView],
) -> Result<f64> {
    let (latents, frames) = latents_and_frames(slots);
    // The hypernetworks run once for all views.
    let prepared = model.prepare(&latents, background)?;
    let renderer = FastRenderer::new(model, &prepared, &frames)?;
    let mut total = 0.0;
    for view in views {
        total += view.mse_by(&renderer)?;
    }
    Ok(total / views.len().max(1) as f64)
}

/// How the newcomers of one view matched the slots kept so far.
#[derive(Clone, Debug, PartialEq)]
pub struct Matching {
    /// For each newcomer, the kept slot that draws the same object, if any.
    pub of: Vec<Option<usize>>,
    /// For each newcomer, whether it takes the place of the kept slot it matched: a pair whose
    /// newcomer draws in more of the views than the kept slot (which its view placed at a depth
    /// from where the other views cannot see it: on a street, the far row's cars seen from the
    /// near row's view); otherwise the kept slot stays.
    pub takes_over: Vec<bool>,
}

/// For each of `newcomers`' slots, the slot of `kept` that draws the same object in `views`,
/// if any. First pairs by decreasing intersection over union of their label maps, summed over
/// the views where both draw (a slot that draws nothing in a view says nothing there: its
/// frame may sit behind that camera), each slot in at most one pair,
/// none under [`MATCH_IOU`]. Then fragments: a newcomer still unmatched whose pixels lie mostly
/// ([`FRAGMENT_SHARE`]) inside one kept slot's, in every view where it draws at least
/// [`FRAGMENT_PIXELS`], is a piece of that slot's object (a view that split an object in two)
/// and matches it too.
pub fn match_slots(
    model: &Colf,
    kept: (&[Slot], &[f32]),
    newcomers: (&[Slot], &[f32]),
    views: &[InputView],
) -> Result<Matching> {
    let mut label_maps = Vec::with_capacity(views.len());
    for view in views {
        label_maps.push((
            labels(model, kept.0, kept.1, view)?,
            labels(model, newcomers.0, newcomers.1, view)?,
        ));
    }
    Ok(match_label_maps(
        kept.0.len(),
        newcomers.0.len(),
        &label_maps,
    ))
}

/// How two slot sets' label maps overlap in one view.
struct ViewOverlap {
    /// Pixels each kept slot draws.
    kept_area: Vec<usize>,
    /// Pixels each newcomer draws.
    new_area: Vec<usize>,
    /// [kept, newcomer]: pixels both draw.
    intersection: Vec<usize>,
}

/// [`match_slots`] on the label maps (0 the background, k + 1 slot k) of `a` kept slots and
/// `b` newcomers, one pair of maps per view.
pub fn match_label_maps(a: usize, b: usize, views: &[(Vec<u32>, Vec<u32>)]) -> Matching {
    // Per view: the kept slots' and the newcomers' areas, and their intersections.
    let mut per_view = Vec::with_capacity(views.len());
    for (la, lb) in views {
        let (mut area_a, mut area_b) = (vec![0usize; a], vec![0usize; b]);
        let mut intersection = vec![0usize; a * b];
        for (&x, &y) in la.iter().zip(lb.iter()) {
            if x > 0 {
                area_a[x as usize - 1] += 1;
            }
            if y > 0 {
                area_b[y as usize - 1] += 1;
            }
            if x > 0 && y > 0 {
                intersection[(x as usize - 1) * b + y as usize - 1] += 1;
            }
        }
        per_view.push(ViewOverlap {
            kept_area: area_a,
            new_area: area_b,
            intersection,
        });
    }
    let draws = |area: usize| area > 0;
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for i in 0..a {
        for j in 0..b {
            // Intersection and union over the views where both draw.
            let (mut both, mut union) = (0, 0);
            for v in per_view
                .iter()
                .filter(|v| draws(v.kept_area[i]) && draws(v.new_area[j]))
            {
                let common = v.intersection[i * b + j];
                both += common;
                union += v.kept_area[i] + v.new_area[j] - common;
            }
            if both > 0 {
                let iou = both as f64 / union as f64;
                if iou >= MATCH_IOU {
                    pairs.push((iou, i, j));
                }
            }
        }
    }
    // Best overlaps first; ties by index, so the matching is deterministic.
    pairs.sort_by(|p, q| q.0.total_cmp(&p.0).then((p.1, p.2).cmp(&(q.1, q.2))));
    let mut taken = vec![false; a];
    let mut matched = vec![None; b];
    let mut takes_over = vec![false; b];
    let views_drawn_in =
        |area: &dyn Fn(&ViewOverlap) -> usize| per_view.iter().filter(|v| draws(area(v))).count();
    for (_, i, j) in pairs {
        if !taken[i] && matched[j].is_none() {
            taken[i] = true;
            matched[j] = Some(i);
            takes_over[j] =
                views_drawn_in(&|v| v.new_area[j]) > views_drawn_in(&|v| v.kept_area[i]);
        }
    }
    for (j, m) in matched.iter_mut().enumerate() {
        if m.is_some() {
            continue;
        }
        // The least share of j's pixels inside kept slot i over the views where j draws.
        let inside = |i: usize| -> Option<f64> {
            per_view
                .iter()
                .filter(|v| v.new_area[j] >= FRAGMENT_PIXELS)
                .map(|v| v.intersection[i * b + j] as f64 / v.new_area[j] as f64)
                .reduce(f64::min)
        };
        *m = (0..a)
            .filter_map(|i| inside(i).map(|share| (share, i)))
            .filter(|&(share, _)| share >= FRAGMENT_SHARE)
            .max_by(|p, q| p.0.total_cmp(&q.0).then(q.1.cmp(&p.1)))
            .map(|(_, i)| i);
    }
    Matching {
        of: matched,
        takes_over,
    }
}

/// Which field draws each of `view`'s compared pixels when `slots` and `background` render it:
/// 0 the background, k + 1 slot k (the compositor's largest weight).
pub fn labels(
    model: &Colf,
    slots: &[Slot],
    background: &[f32],
    view: &InputView,
) -> Result<Vec<u32>> {
    let (latents, frames) = latents_and_frames(slots);
    let prepared = model.prepare(&latents, background)?;
    let pixels = &view.compared;
    let out = if model.config().is_volumetric() {
        model.render_rays(&prepared, &frames, &pixels.origins, &pixels.dirs)?
    } else {
        FastRenderer::new(model, &prepared, &frames)?.render(
            &pixels.origins,
            &pixels.dirs,
            None,
            None,
        )?
    };
    Ok(crate::render::output::argmax_labels(
        &out.weights,
        out.fields,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::look_at;
    use crate::model::Config;
    use glam::DVec3;

    fn image(size: u32, phase: u32) -> RgbImage32 {
        let data = (0..3 * size * size)
            .map(|i| (((i + phase) * 37 % 101) as f32) / 100.0)
            .collect();
        RgbImage32 {
            w: size,
            h: size,
            data,
        }
    }

    fn camera(size: u32, x: f64) -> Frame {
        Frame {
            file_path: None,
            intrinsics: crate::camera::Intrinsics::from_fov(size, size, 49.13),
            camera_to_world: look_at(DVec3::new(x, -8.0, 9.0), DVec3::ZERO, DVec3::Z).unwrap(),
        }
    }

    fn options() -> EncodeOptions {
        EncodeOptions {
            source: "ignored".into(),
            ..EncodeOptions::one_pass(4)
        }
    }

    #[test]
    fn one_view_is_the_single_image_encoding() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let img = image(16, 0);
        let input = ViewInput {
            image: &img,
            camera: camera(16, 0.0),
            source: "a.png".into(),
        };
        let (codes, report) = encode_views(&model, &[input], &options()).unwrap();
        let single = super::super::encode_image(
            &model,
            &img,
            &EncodeOptions {
                camera: Some(camera(16, 0.0)),
                source: "a.png".into(),
                ..options()
            },
        )
        .unwrap();
        assert_eq!(codes, single);
        assert_eq!(report.proposed, vec![codes.slots.len()]);
        assert!(encode_views(&model, &[], &options()).is_err());
    }

    #[test]
    fn slots_that_draw_the_same_pixels_are_matched_once() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let img = image(16, 0);
        let cam = camera(16, 0.0);
        let view = InputView::new(&cam, &img);
        let (slots, background) = super::super::encode_once(&model, &view, &options(), 3).unwrap();
        // A set against itself: every slot that draws a pixel is its own match, and only its,
        // and stays.
        let labels = labels(&model, &slots, &background, &view).unwrap();
        let matched = match_slots(
            &model,
            (&slots, &background),
            (&slots, &background),
            std::slice::from_ref(&view),
        )
        .unwrap();
        for (k, m) in matched.of.iter().enumerate() {
            let draws = labels.contains(&(k as u32 + 1));
            assert_eq!(*m, draws.then_some(k), "slot {k}");
        }
        assert!(matched.of.iter().any(|m| m.is_some()));
        assert!(matched.takes_over.iter().all(|t| !t));
        // Against no slots: nothing matches.
        let none = match_slots(&model, (&[], &background), (&slots, &background), &[view]).unwrap();
        assert!(none.of.iter().all(|m| m.is_none()));
    }

    /// A label map of 16 pixels: pixels `ranges[k].0..ranges[k].1` drawn by slot k, the rest
    /// background.
    fn label_map(ranges: &[(usize, usize)]) -> Vec<u32> {
        let mut map = vec![0u32; 16];
        for (k, &(start, end)) in ranges.iter().enumerate() {
            map[start..end].fill(k as u32 + 1);
        }
        map
    }

    #[test]
    fn label_maps_match_by_overlap_then_by_fragment() {
        // Kept: slot 0 on pixels 0–9, slot 1 on 12–15.
        let kept = label_map(&[(0, 10), (12, 16)]);
        // Newcomer 0 covers most of slot 0 (IoU 0.6) and pairs with it; newcomer 1 is the rest
        // of that object, all 4 of its pixels inside slot 0: a fragment, it matches slot 0 too.
        let split = label_map(&[(4, 10), (0, 4)]);
        assert_eq!(
            match_label_maps(2, 2, &[(kept.clone(), split.clone())]).of,
            vec![Some(0), Some(0)]
        );
        // A second view where newcomer 1 lies outside slot 0: not a fragment (every view where
        // it draws must agree), and too little overlap with anything to pair.
        let elsewhere = label_map(&[(4, 10), (10, 14)]);
        assert_eq!(
            match_label_maps(2, 2, &[(kept.clone(), split), (kept.clone(), elsewhere)]).of,
            vec![Some(0), None]
        );
        // A newcomer where no kept slot draws is a new object; one drawing too few pixels to
        // judge is not a fragment.
        assert_eq!(
            match_label_maps(2, 2, &[(kept.clone(), label_map(&[(10, 12), (12, 13)]))]).of,
            vec![None, Some(1)]
        );
        assert_eq!(
            match_label_maps(2, 1, &[(kept, label_map(&[(10, 12)]))]).of,
            vec![None]
        );
    }

    /// A slot that draws nothing in a view (its frame behind that camera) is judged on the
    /// views where both draw, and the slot that draws in more views takes the pair's place.
    #[test]
    fn a_slot_invisible_in_a_view_is_judged_where_both_draw() {
        // View a: kept slot 0 on pixels 0–5, newcomer 0 on 3–8 (IoU 3/9). View b: the kept
        // slot draws nothing, the newcomer 8 pixels; summed over both views the IoU would be
        // 3/17, under MATCH_IOU.
        let view_a = (label_map(&[(0, 6)]), label_map(&[(3, 9)]));
        let view_b = (label_map(&[]), label_map(&[(2, 10)]));
        let matching = match_label_maps(1, 1, &[view_a.clone(), view_b.clone()]);
        assert_eq!(matching.of, vec![Some(0)]);
        assert_eq!(matching.takes_over, vec![true]);
        // Both drawing in both views: the kept slot stays.
        let view_b_both = (label_map(&[(2, 10)]), label_map(&[(2, 10)]));
        let matching = match_label_maps(1, 1, &[view_a.clone(), view_b_both]);
        assert_eq!(
            (matching.of, matching.takes_over),
            (vec![Some(0)], vec![false])
        );
        // Disagreeing where both draw still keeps them apart: in view b the kept slot draws
        // pixels 10–16 and the newcomer 2–10 (IoU 3/23 over both views).
        let view_b_apart = (label_map(&[(10, 16)]), label_map(&[(2, 10)]));
        let matching = match_label_maps(1, 1, &[view_a, view_b_apart]);
        assert_eq!(matching.of, vec![None]);
    }

    #[test]
    fn the_same_view_twice_adds_no_slot_that_draws() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let img = image(16, 0);
        let input = |source: &str| ViewInput {
            image: &img,
            camera: camera(16, 0.0),
            source: source.into(),
        };
        let (codes, report) = encode_views(&model, &[input("a"), input("b")], &options()).unwrap();
        assert_eq!(report.proposed.len(), 2);
        // Every slot of the second view that draws a pixel found its twin.
        let cam = camera(16, 0.0);
        let view = InputView::new(&cam, &img);
        let drawn: Vec<u32> = labels(&model, &codes.slots, &codes.background, &view).unwrap();
        for (k, slot) in codes.slots.iter().enumerate() {
            if slot.source.starts_with("b#") {
                assert!(!drawn.contains(&(k as u32 + 1)), "{} draws", slot.source);
            }
        }
        assert!(report.matched > 0);
        // Same inputs, same bytes.
        let (again, _) = encode_views(&model, &[input("a"), input("b")], &options()).unwrap();
        assert_eq!(codes, again);
    }

    /// The guard after the agreed slots: slots that draw the views worse than those before
    /// them are undone, slots that draw them as well are kept.
    #[test]
    fn slots_that_draw_the_views_worse_are_undone() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let cam = camera(16, 0.0);
        let img = image(16, 0);
        let (slots, background) =
            super::super::encode_once(&model, &InputView::new(&cam, &img), &options(), 3).unwrap();
        // A view these slots draw exactly: their own render.
        let codes = Codes {
            slots: slots.clone(),
            background: background.clone(),
            model: model.identity().unwrap(),
        };
        let scene = crate::render::PreparedScene::new(&model, &codes, "test").unwrap();
        let render = scene.render_frame(&model, &cam).unwrap();
        let drawn = RgbImage32 {
            w: 16,
            h: 16,
            data: render.rgb,
        };
        let view = InputView::new(&cam, &drawn);
        let before = (slots.clone(), background.clone());
        let mut moved = slots.clone();
        for slot in &mut moved {
            slot.latent.iter_mut().for_each(|v| *v += 1.0);
        }
        let (kept, undone) = no_worse_than(
            &model,
            (moved, background.clone()),
            before.clone(),
            &[&view],
        )
        .unwrap();
        assert!(undone);
        assert_eq!(kept, before);
        let (kept, undone) =
            no_worse_than(&model, before.clone(), (Vec::new(), background), &[&view]).unwrap();
        assert!(!undone, "the slots' own render is drawn worse without them");
        assert_eq!(kept, before);
    }

    #[test]
    fn triangulation_refines_the_kept_slots_from_the_third_view_on() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let images: Vec<RgbImage32> = (0..3).map(|v| image(16, 7 * v)).collect();
        let inputs: Vec<ViewInput> = images
            .iter()
            .enumerate()
            .map(|(v, img)| ViewInput {
                image: img,
                camera: camera(16, 2.0 * v as f64 - 2.0),
                source: format!("v{v}"),
            })
            .collect();
        let triangulated = EncodeOptions {
            triangulate_steps: 3,
            ..options()
        };
        // Two views: nothing to triangulate before matching, the same bytes as without.
        let (two, report) = encode_views(&model, &inputs[..2], &triangulated).unwrap();
        assert_eq!(report.triangulated, 0);
        assert_eq!(
            two,
            encode_views(&model, &inputs[..2], &options()).unwrap().0
        );
        // Three: the first two views' slots are refined before the third's are matched.
        let (three, report) = encode_views(&model, &inputs, &triangulated).unwrap();
        assert_eq!(report.triangulated, 3);
        let (plain, plain_report) = encode_views(&model, &inputs, &options()).unwrap();
        assert_eq!(plain_report.triangulated, 0);
        assert_ne!(three, plain);
        assert_eq!(
            three,
            encode_views(&model, &inputs, &triangulated).unwrap().0
        );
    }
}
