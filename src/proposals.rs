//! Object proposals from an image alone: which pixels are objects, grouped into instances,
//! without any ground-truth mask.
//!
//! In a CLEVR-like view the floor fills the frame and changes slowly across it (constant in
//! colf-synth's analytic scenes, a smooth light falloff in Blender's); a room adds walls and a
//! wooden or tiled floor. So:
//! 1. **Background**: a low-order polynomial in the pixel coordinates is fitted to each colour
//!    channel by trimmed least squares — refitted on the pixels it explains, so objects (a few
//!    per cent of the view) do not pull it. A wall is a large region of one chromaticity far
//!    from that floor and touching the view's border: it gets a surface of its own (up to
//!    `layers` of them), and the floor is refitted without it.
//! 2. **Candidates**: pixels farther from their surface than `threshold` in some channel. A
//!    textured surface (its trimmed fit's residuals spread widely) has a wider tolerance,
//!    `texture` × that spread: pixels between `threshold` and it are [`UNSURE`], the grain of
//!    the wood or a dim object of its colour — unless their hue (chromaticity) is farther from
//!    the surface's than `hue_texture` × the surface's own hue spread: a blue chair on brown
//!    parquet or on grey stripes.
//! 3. **Lighting**: a candidate that is a uniformly darkened or brightened copy of the
//!    background (equal ratios in R, G and B, below `shadow_ratio` or above its inverse) is a
//!    shadow or a light's bright spot the polynomial did not follow, not an object, and is
//!    marked [`UNSURE`]: it belongs to no instance (a grey object can look like one too).
//! 4. **Instances**: 8-connected components of the remaining candidates, numbered 1, 2, … from
//!    the largest; components smaller than `min_area` of the view, and a `ring` of pixels
//!    around every instance (soft, antialiased edges), are [`UNSURE`] as well.
//!
//! The trainer uses proposals where it would use mask files (`colf-train --proposals`): ids
//! are local to each view (the same object may get different ids in two views), and
//! [`UNSURE`] pixels are left to the colour loss. `colf-train propose` writes them as mask PNGs
//! and scores them against ground truth where there is some.

use crate::image_io::RgbImage32;
use std::collections::BTreeMap;

/// Proposal id of a pixel that is neither background nor a proposed object: shadows, specks,
/// instance borders. Losses built on proposals ignore it.
pub const UNSURE: u8 = 255;

/// Whether a mask or proposal id names an object to supervise: neither background (0) nor
/// [`UNSURE`].
pub fn is_instance(id: u8) -> bool {
    id != 0 && id != UNSURE
}

/// Per pixel of a proposal map `ids`, 1 on an object and 0 elsewhere (unsure pixels too).
pub fn object_pixels(ids: &[u8]) -> Vec<f32> {
    ids.iter()
        .map(|&id| f32::from(u8::from(is_instance(id))))
        .collect()
}

/// The proposal recipe's settings (the defaults were chosen on 25 training scenes of
/// colf-synth's analytic clevr567 and 25 of its Blender engine, scored against their masks).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProposalParams {
    /// Total degree of the background polynomial in x and y.
    pub degree: usize,
    /// Trimming passes of the background fit.
    pub passes: usize,
    /// A pixel is a candidate when some channel differs from the background by more (sRGB).
    pub threshold: f32,
    /// Lighting, not objects: the mean of the three channel ratios to the background is below
    /// this (a shadow) or above its inverse (a bright spot)…
    pub shadow_ratio: f32,
    /// …and no channel's ratio is farther from that mean than this.
    pub shadow_spread: f32,
    /// Neighbouring candidates join one instance only if their chromaticities (r, g, b over
    /// r + g + b) differ by less than this in every channel: shading changes brightness, not
    /// chromaticity, so this splits objects of different colours that touch in the view.
    pub chroma_edge: f32,
    /// Fragments smaller than this share of the view (a highlight, an antialiased edge) join
    /// the neighbouring instance they share the longest border with.
    pub merge_below: f32,
    /// Instances smaller than this share of the view are [`UNSURE`].
    pub min_area: f32,
    /// Width in pixels of the [`UNSURE`] band around each instance.
    pub ring: usize,
    /// At most this many background surfaces besides the floor (walls, a sky).
    pub layers: usize,
    /// A background surface covers at least this share of the view.
    pub layer_area: f32,
    /// Total degree of a background surface's polynomial.
    pub layer_degree: usize,
    /// A surface's tolerance is at least this many times its spread (the 75th percentile of
    /// its pixels' residuals), so textured floors do not become candidates.
    pub texture: f32,
    /// …but a pixel whose chromaticity is farther from its surface's than this many times the
    /// surface's own chromaticity spread (and `chroma_edge`) is a candidate all the same: an
    /// object of another hue on a grain of one hue.
    pub hue_texture: f32,
}

impl Default for ProposalParams {
    fn default() -> Self {
        ProposalParams {
            degree: 3,
            passes: 5,
            threshold: 0.08,
            shadow_ratio: 0.97,
            shadow_spread: 0.06,
            chroma_edge: 0.08,
            merge_below: 0.002,
            min_area: 0.001,
            ring: 1,
            layers: 3,
            layer_area: 0.05,
            layer_degree: 2,
            texture: 2.5,
            hue_texture: 4.0,
        }
    }
}

/// Proposal ids of `image`, row-major: 0 background, 1…254 instances from the largest, and
/// [`UNSURE`]. Instances past 254 (never seen in practice) are [`UNSURE`].
pub fn propose(image: &RgbImage32, params: &ProposalParams) -> Vec<u8> {
    if image.data.is_empty() {
        return Vec::new();
    }
    let chroma = chromaticities(image);
    let background = background_layers(image, &chroma, params);
    instances(image, &chroma, &background, params)
}

/// Proposal ids of `image` (as [`propose`]'s) against a known background: `background` is
/// what the view shows without its objects (RGB, row-major, the image's size), for scenes
/// whose background does not change — a static background field rendered at the view's camera
/// (the city's street). A pixel is an object candidate where it differs from that render by
/// more than `params.threshold` in some channel *and* in chromaticity by more than
/// `render_hue` (the render is a little blurred, so a building's edge differs in brightness but
/// not in hue); other differences (edges, a car's shadow, a grey car) are [`UNSURE`].
/// Instances are then grouped as in [`propose`].
pub fn propose_against(
    image: &RgbImage32,
    background: &[f32],
    render_hue: f32,
    params: &ProposalParams,
) -> anyhow::Result<Vec<u8>> {
    if background.len() != image.data.len() {
        anyhow::bail!(
            "object proposals: the background render has {} values, the {}x{} image {}",
            background.len(),
            image.w,
            image.h,
            image.data.len()
        );
    }
    let n = background.len() / 3;
    let known = Background {
        colour: background.to_vec(),
        // Any brightness difference within the same hue is left unsure, not background.
        tolerance: vec![f32::INFINITY; n],
        chroma_tolerance: vec![render_hue; n],
    };
    Ok(instances(image, &chromaticities(image), &known, params))
}

/// Steps 2–4 of the recipe (module docs) on a view's `background`: candidates, lighting,
/// instances.
fn instances(
    image: &RgbImage32,
    chroma: &[[f32; 3]],
    background: &Background,
    params: &ProposalParams,
) -> Vec<u8> {
    let (w, h) = (image.w as usize, image.h as usize);
    let n = w * h;
    let Background {
        colour: background,
        tolerance,
        chroma_tolerance,
    } = background;
    let data = &image.data;
    let mut object = vec![false; n];
    let mut ids = vec![0u8; n];
    for p in 0..n {
        let pixel = &data[3 * p..3 * p + 3];
        let floor = &background[3 * p..3 * p + 3];
        let distance = (0..3)
            .map(|c| (pixel[c] - floor[c]).abs())
            .fold(0f32, f32::max);
        if distance <= params.threshold {
            continue;
        }
        let other_hue =
            chroma_distance(image, p, background).is_some_and(|d| d > chroma_tolerance[p]);
        if distance <= tolerance[p] && !other_hue {
            // Within the grain of a textured surface: maybe an object of its colour, maybe
            // the surface; left to the colour loss.
            ids[p] = UNSURE;
            continue;
        }
        let ratios: [f32; 3] = std::array::from_fn(|c| pixel[c] / floor[c].max(1e-3));
        let mean = (ratios[0] + ratios[1] + ratios[2]) / 3.0;
        let spread = ratios
            .iter()
            .map(|r| (r - mean).abs())
            .fold(0.0f32, f32::max);
        if (mean < params.shadow_ratio || mean > 1.0 / params.shadow_ratio)
            && spread < params.shadow_spread
        {
            ids[p] = UNSURE;
        } else {
            object[p] = true;
        }
    }
    let min_area = ((params.min_area as f64 * n as f64).ceil() as usize).max(1);
    let fragments = components_8(&object, w, h, |p, q| same_chroma(chroma, p, q, params));
    let merge_below = (params.merge_below as f64 * n as f64).ceil() as usize;
    let mut components = merge_fragments(fragments, w, h, merge_below);
    // Largest first; ties by the first pixel, so the numbering is deterministic.
    components.sort_by_key(|c| (std::cmp::Reverse(c.len()), c[0]));
    let mut next = 1u16;
    for component in &components {
        let id = if component.len() >= min_area && next < UNSURE as u16 {
            next += 1;
            (next - 1) as u8
        } else {
            UNSURE
        };
        for &p in component {
            ids[p] = id;
        }
    }
    if params.ring > 0 {
        let instance: Vec<bool> = ids.iter().map(|&id| is_instance(id)).collect();
        for (p, id) in ids.iter_mut().enumerate() {
            if *id == 0 && any_within(w, h, p, params.ring, |q| instance[q]) {
                *id = UNSURE;
            }
        }
    }
    ids
}

/// The chromaticity of an RGB colour: r, g, b over r + g + b (the sum kept above 1e-3).
fn chromaticity(rgb: &[f32]) -> [f32; 3] {
    let sum = (rgb[0] + rgb[1] + rgb[2]).max(1e-3);
    [rgb[0] / sum, rgb[1] / sum, rgb[2] / sum]
}

/// Every pixel's [`chromaticity`], row-major.
fn chromaticities(image: &RgbImage32) -> Vec<[f32; 3]> {
    image.data.chunks_exact(3).map(chromaticity).collect()
}

/// Whether neighbouring pixels `p` and `q` have nearly the same chromaticity (`chroma`, from
/// [`chromaticities`]; within `params.chroma_edge` in every channel).
fn same_chroma(chroma: &[[f32; 3]], p: usize, q: usize, params: &ProposalParams) -> bool {
    (0..3).all(|c| (chroma[p][c] - chroma[q][c]).abs() < params.chroma_edge)
}

/// The background under every pixel: its colour (RGB, row-major) and how far a pixel may stray
/// from it and still be background (its surface's tolerance).
///
/// The floor is fitted first, to the whole view. A room's wall, a sky or a second ground
/// plane is not that polynomial, so its pixels are far from it: they make a large component of
/// same-chromaticity candidates touching the view's border, which an object standing in the
/// scene rarely does. Up to `params.layers` times, the largest such component (≥
/// `params.layer_area` of the view) gets a surface of its own, fitted to it alone; if that
/// surface explains at least `params.layer_area` of the view, those pixels are its background
/// (else the search stops), and the floor is refitted without them. A surface's tolerance is
/// `params.threshold`, or `params.texture` times its own spread where that is larger, so a
/// wooden or tiled floor's grain is not taken for objects.
fn background_layers(
    image: &RgbImage32,
    chroma: &[[f32; 3]],
    params: &ProposalParams,
) -> Background {
    let n = (image.w * image.h) as usize;
    let (w, h) = (image.w as usize, image.h as usize);
    let tolerance_of = |surface: &Surface| params.threshold.max(params.texture * surface.spread);
    let distance = |p: usize, colour: &[f32]| {
        (0..3)
            .map(|c| (image.data[3 * p + c] - colour[3 * p + c]).abs())
            .fold(0f32, f32::max)
    };
    let on_border = |p: usize| {
        let (x, y) = (p % w, p / w);
        x == 0 || y == 0 || x + 1 == w || y + 1 == h
    };
    let layer_area = ((params.layer_area as f64 * n as f64).ceil() as usize).max(1);
    let mut claimed = vec![false; n];
    // Which surface each pixel's background is: 0 the floor, k the k-th layer.
    let mut surface_of = vec![0usize; n];
    let floor = fit_surface(image, &vec![true; n], params.degree, params.passes);
    let mut tolerance = vec![tolerance_of(&floor); n];
    let mut background = floor.colour;
    for layer in 1..=params.layers {
        let candidate: Vec<bool> = (0..n)
            .map(|p| !claimed[p] && distance(p, &background) > params.threshold)
            .collect();
        let mut regions: Vec<Vec<usize>> =
            components_8(&candidate, w, h, |p, q| same_chroma(chroma, p, q, params))
                .into_iter()
                .filter(|c| c.len() >= layer_area && c.iter().any(|&p| on_border(p)))
                .collect();
        regions.sort_by_key(|c| (std::cmp::Reverse(c.len()), c[0]));
        let unclaimed = claimed.iter().filter(|&&c| !c).count();
        // The largest region a surface of its own explains well enough. The floor stays the
        // largest surface: were this one larger than what is left, the floor's refit on the
        // rest could bend through the objects standing on it.
        let found = regions.iter().find_map(|region| {
            let mut inside = vec![false; n];
            for &p in region {
                inside[p] = true;
            }
            let surface = fit_surface(image, &inside, params.layer_degree, params.passes);
            let surface_tolerance = tolerance_of(&surface);
            // The pixels it explains, grown from the region into its neighbours of the same
            // chromaticity that it explains too: the floor's first fit bent towards the wall,
            // so the wall's pixels nearest the floor's were not far from it.
            let fits = |p: usize| distance(p, &surface.colour) <= surface_tolerance;
            let mut explained: Vec<usize> = region.iter().copied().filter(|&p| fits(p)).collect();
            let mut taken = vec![false; n];
            for &p in &explained {
                taken[p] = true;
            }
            let mut next = 0;
            while next < explained.len() {
                let p = explained[next];
                next += 1;
                for q in neighbours_8(p, w, h) {
                    if !taken[q] && !claimed[q] && fits(q) && same_chroma(chroma, p, q, params) {
                        taken[q] = true;
                        explained.push(q);
                    }
                }
            }
            (explained.len() >= layer_area && 2 * explained.len() <= unclaimed).then_some((
                surface,
                surface_tolerance,
                explained,
            ))
        });
        let Some((surface, surface_tolerance, explained)) = found else {
            break;
        };
        for &p in &explained {
            claimed[p] = true;
            surface_of[p] = layer;
            background[3 * p..3 * p + 3].copy_from_slice(&surface.colour[3 * p..3 * p + 3]);
            tolerance[p] = surface_tolerance;
        }
        // The floor's fit no longer has to bend towards the surface just found.
        let rest: Vec<bool> = claimed.iter().map(|&c| !c).collect();
        let floor = fit_surface(image, &rest, params.degree, params.passes);
        let floor_tolerance = tolerance_of(&floor);
        for p in (0..n).filter(|&p| !claimed[p]) {
            background[3 * p..3 * p + 3].copy_from_slice(&floor.colour[3 * p..3 * p + 3]);
            tolerance[p] = floor_tolerance;
        }
    }
    // Each surface's chromaticity spread over the pixels it explains: a grain of one hue (wood,
    // grey stripes) leaves it small, so an object of another hue stands out from the grain even
    // where its brightness does not.
    let surfaces = surface_of.iter().max().map_or(0, |&k| k + 1);
    let mut chroma_tolerance = vec![f32::INFINITY; surfaces];
    for (k, slot) in chroma_tolerance.iter_mut().enumerate() {
        let mut spread: Vec<f32> = (0..n)
            .filter(|&p| surface_of[p] == k && distance(p, &background) <= tolerance[p])
            .filter_map(|p| chroma_distance(image, p, &background))
            .collect();
        if spread.is_empty() {
            continue;
        }
        let at = (spread.len() * 3 / 4).min(spread.len() - 1);
        let (_, q75, _) = spread.select_nth_unstable_by(at, f32::total_cmp);
        *slot = params.chroma_edge.max(params.hue_texture * *q75);
    }
    Background {
        colour: background,
        tolerance,
        chroma_tolerance: surface_of.iter().map(|&k| chroma_tolerance[k]).collect(),
    }
}

/// The background under every pixel: see [`background_layers`].
struct Background {
    /// RGB, row-major.
    colour: Vec<f32>,
    /// How far (largest channel difference) a pixel may stray from it and be its surface's.
    tolerance: Vec<f32>,
    /// How far a pixel's chromaticity may stray from it and be its surface's grain.
    chroma_tolerance: Vec<f32>,
}

/// The largest channel difference between the chromaticities of pixel `p` and of `colour` at
/// `p`; None where either is too dark for its chromaticity to mean anything.
fn chroma_distance(image: &RgbImage32, p: usize, colour: &[f32]) -> Option<f32> {
    let bright = |rgb: &[f32]| (rgb[0] + rgb[1] + rgb[2] >= 0.3).then(|| chromaticity(rgb));
    let a = bright(&image.data[3 * p..3 * p + 3])?;
    let b = bright(&colour[3 * p..3 * p + 3])?;
    Some((0..3).map(|c| (a[c] - b[c]).abs()).fold(0f32, f32::max))
}

/// How a view's proposals compare with its ground-truth mask (only to report their quality:
/// training never sees the masks).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ProposalScore {
    /// FG-ARI of the proposals: the ARI over the ground truth's object pixels, with background
    /// and [`UNSURE`] counting as labels of their own. None when the view shows no object.
    pub fg_ari: Option<f64>,
    /// The ARI over the object pixels the proposals put in an instance: how well the instances
    /// group what they cover.
    pub fg_ari_on_instances: Option<f64>,
    /// Share of the ground truth's object pixels the proposals call background (they teach the
    /// background to take objects).
    pub objects_called_background: f64,
    /// Share of the ground truth's object pixels the proposals leave [`UNSURE`] (to the colour
    /// loss alone).
    pub objects_unsure: f64,
    /// Share of the instance pixels that are background in the ground truth (shadows, floor).
    pub instances_on_background: f64,
    /// Share of the view marked [`UNSURE`].
    pub unsure: f64,
}

/// Scores proposal ids against a ground-truth mask of the same size (0 = background).
pub fn score(ids: &[u8], truth: &[u8]) -> anyhow::Result<ProposalScore> {
    if ids.len() != truth.len() {
        anyhow::bail!(
            "the proposals have {} pixels and the mask {}",
            ids.len(),
            truth.len()
        );
    }
    let as_u32 = |v: &[u8]| v.iter().map(|&x| x as u32).collect::<Vec<u32>>();
    let fg_ari = crate::metrics::fg_ari(&as_u32(ids), &as_u32(truth))?;
    let (on_pred, on_truth): (Vec<u32>, Vec<u32>) = ids
        .iter()
        .zip(truth)
        .filter(|&(&p, &t)| t != 0 && is_instance(p))
        .map(|(&p, &t)| (p as u32, t as u32))
        .unzip();
    let fg_ari_on_instances = if on_truth.is_empty() {
        None
    } else {
        Some(crate::metrics::ari(&on_pred, &on_truth)?)
    };
    let share = |count: usize, of: usize| {
        if of == 0 {
            0.0
        } else {
            count as f64 / of as f64
        }
    };
    let objects = truth.iter().filter(|&&t| t != 0).count();
    let instances = ids.iter().filter(|&&p| is_instance(p)).count();
    let pairs = || ids.iter().zip(truth);
    Ok(ProposalScore {
        fg_ari,
        fg_ari_on_instances,
        objects_called_background: share(
            pairs().filter(|&(&p, &t)| t != 0 && p == 0).count(),
            objects,
        ),
        objects_unsure: share(
            pairs().filter(|&(&p, &t)| t != 0 && p == UNSURE).count(),
            objects,
        ),
        instances_on_background: share(
            pairs().filter(|&(&p, &t)| t == 0 && is_instance(p)).count(),
            instances,
        ),
        unsure: share(ids.iter().filter(|&&p| p == UNSURE).count(), ids.len()),
    })
}

/// The background colour of every pixel (RGB, row-major): per channel, a polynomial of total
/// degree `degree` in x, y ∈ [−1, 1], fitted by least squares, then `passes − 1` times refitted
/// on the pixels whose largest channel residual is under 2.5× the 75th percentile of the kept
/// pixels' (at least 0.01).
pub fn fit_background(image: &RgbImage32, degree: usize, passes: usize) -> Vec<f32> {
    let everywhere = vec![true; (image.w * image.h) as usize];
    fit_surface(image, &everywhere, degree, passes).colour
}

/// A smooth surface fitted to part of a view: its colour at every pixel, and how far the
/// pixels it was fitted on stray from it.
struct Surface {
    colour: Vec<f32>,
    /// The 75th percentile of the largest channel residual over the pixels kept by the last
    /// trimming pass: the surface's own texture and noise.
    spread: f32,
}

/// [`fit_background`] on the pixels of `region` only (the trimming starts from them); the
/// polynomial is evaluated everywhere.
fn fit_surface(image: &RgbImage32, region: &[bool], degree: usize, passes: usize) -> Surface {
    let (w, h) = (image.w as usize, image.h as usize);
    let n = w * h;
    let terms: Vec<(usize, usize)> = (0..=degree)
        .flat_map(|i| (0..=degree - i).map(move |j| (i, j)))
        .collect();
    let basis = |p: usize| -> Vec<f64> {
        let x = ((p % w) as f64 + 0.5) / w as f64 * 2.0 - 1.0;
        let y = ((p / w) as f64 + 0.5) / h as f64 * 2.0 - 1.0;
        terms
            .iter()
            .map(|&(i, j)| x.powi(i as i32) * y.powi(j as i32))
            .collect()
    };
    let rows: Vec<Vec<f64>> = (0..n).map(basis).collect();
    let mut keep = region.to_vec();
    let mut fitted = vec![0f32; 3 * n];
    let mut spread = 0f32;
    for pass in 0..passes.max(1) {
        let coefficients = least_squares(&rows, &image.data, &keep, terms.len());
        let mut residuals = Vec::with_capacity(n);
        for (p, row) in rows.iter().enumerate() {
            let mut worst = 0f32;
            for c in 0..3 {
                let v: f64 = row.iter().zip(&coefficients[c]).map(|(a, b)| a * b).sum();
                fitted[3 * p + c] = v as f32;
                worst = worst.max((image.data[3 * p + c] - v as f32).abs());
            }
            residuals.push(worst);
        }
        let mut kept: Vec<f32> = (0..n).filter(|&p| keep[p]).map(|p| residuals[p]).collect();
        if kept.is_empty() {
            break;
        }
        let at = ((kept.len() * 3) / 4).min(kept.len() - 1);
        let (_, q75, _) = kept.select_nth_unstable_by(at, f32::total_cmp);
        spread = *q75;
        if pass + 1 == passes.max(1) {
            break;
        }
        let limit = (*q75 * 2.5).max(0.01);
        let next: Vec<bool> = (0..n).map(|p| region[p] && residuals[p] < limit).collect();
        // Too few pixels left to fit the polynomial: keep the previous fit's pixels.
        if next.iter().filter(|&&k| k).count() < 4 * terms.len() {
            break;
        }
        keep = next;
    }
    Surface {
        colour: fitted,
        spread,
    }
}

/// Per channel, the coefficients minimising Σ_kept (row·coef − value)², from the normal
/// equations (solved with partial pivoting; a singular system, e.g. too few pixels, falls back
/// to the kept pixels' mean colour).
fn least_squares(rows: &[Vec<f64>], rgb: &[f32], keep: &[bool], m: usize) -> [Vec<f64>; 3] {
    let mut normal = vec![0f64; m * m];
    let mut rhs = [vec![0f64; m], vec![0f64; m], vec![0f64; m]];
    let (mut sum, mut count) = ([0f64; 3], 0usize);
    for (p, row) in rows.iter().enumerate().filter(|&(p, _)| keep[p]) {
        for a in 0..m {
            for b in 0..m {
                normal[a * m + b] += row[a] * row[b];
            }
            for c in 0..3 {
                rhs[c][a] += row[a] * rgb[3 * p + c] as f64;
            }
        }
        for c in 0..3 {
            sum[c] += rgb[3 * p + c] as f64;
        }
        count += 1;
    }
    std::array::from_fn(|c| {
        solve(normal.clone(), rhs[c].clone(), m).unwrap_or_else(|| {
            let mut constant = vec![0f64; m];
            // Term (0, 0) is the constant and comes first.
            constant[0] = sum[c] / count.max(1) as f64;
            constant
        })
    })
}

/// Solves the m×m system `a x = b` by Gaussian elimination with partial pivoting; None when it
/// is (numerically) singular.
fn solve(mut a: Vec<f64>, mut b: Vec<f64>, m: usize) -> Option<Vec<f64>> {
    let scale = a.iter().fold(0f64, |s, v| s.max(v.abs())).max(1e-300);
    for col in 0..m {
        let pivot =
            (col..m).max_by(|&i, &j| a[i * m + col].abs().total_cmp(&a[j * m + col].abs()))?;
        if a[pivot * m + col].abs() <= 1e-12 * scale {
            return None;
        }
        if pivot != col {
            for k in 0..m {
                a.swap(pivot * m + k, col * m + k);
            }
            b.swap(pivot, col);
        }
        for row in col + 1..m {
            let f = a[row * m + col] / a[col * m + col];
            if f != 0.0 {
                for k in col..m {
                    a[row * m + k] -= f * a[col * m + k];
                }
                b[row] -= f * b[col];
            }
        }
    }
    let mut x = vec![0f64; m];
    for row in (0..m).rev() {
        let tail: f64 = (row + 1..m).map(|k| a[row * m + k] * x[k]).sum();
        x[row] = (b[row] - tail) / a[row * m + row];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Merges every component smaller than `below` pixels into the neighbouring component (8-
/// connected) it shares the most border pixel pairs with, smallest first, until none is left
/// that has a neighbour. Each result keeps its pixels sorted.
fn merge_fragments(
    mut components: Vec<Vec<usize>>,
    w: usize,
    h: usize,
    below: usize,
) -> Vec<Vec<usize>> {
    let mut owner = vec![usize::MAX; w * h];
    for (i, c) in components.iter().enumerate() {
        for &p in c {
            owner[p] = i;
        }
    }
    loop {
        // The smallest fragment with a neighbour (ties: the first pixel), and that neighbour.
        let mut best: Option<(usize, usize, usize)> = None; // (size, fragment, into)
        for (i, c) in components.iter().enumerate() {
            if c.is_empty()
                || c.len() >= below
                || best.is_some_and(|b| (b.0, components[b.1][0]) <= (c.len(), c[0]))
            {
                continue;
            }
            let mut contacts: BTreeMap<usize, usize> = BTreeMap::new();
            for &p in c {
                for q in neighbours_8(p, w, h) {
                    let o = owner[q];
                    if o != usize::MAX && o != i {
                        *contacts.entry(o).or_default() += 1;
                    }
                }
            }
            if let Some((&into, _)) = contacts
                .iter()
                .max_by_key(|&(&o, &k)| (k, std::cmp::Reverse(o)))
            {
                best = Some((c.len(), i, into));
            }
        }
        let Some((_, fragment, into)) = best else {
            break;
        };
        let moved = std::mem::take(&mut components[fragment]);
        for &p in &moved {
            owner[p] = into;
        }
        components[into].extend(moved);
        components[into].sort_unstable();
    }
    components.retain(|c| !c.is_empty());
    components
}

/// The 8 neighbours of pixel `p` inside a w×h grid.
fn neighbours_8(p: usize, w: usize, h: usize) -> impl Iterator<Item = usize> {
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    (-1..=1isize)
        .flat_map(move |dy| (-1..=1isize).map(move |dx| (x + dx, y + dy)))
        .filter(move |&(nx, ny)| {
            (nx, ny) != (x, y) && nx >= 0 && ny >= 0 && nx < w as isize && ny < h as isize
        })
        .map(move |(nx, ny)| ny as usize * w + nx as usize)
}

/// The 8-connected components of the `true` pixels of a w×h grid, where two neighbours are
/// connected only if `joined(p, q)`; each a list of pixel indices starting with its first pixel
/// in row-major order.
fn components_8(
    on: &[bool],
    w: usize,
    h: usize,
    joined: impl Fn(usize, usize) -> bool,
) -> Vec<Vec<usize>> {
    let mut seen = vec![false; on.len()];
    let mut out = Vec::new();
    for start in 0..on.len() {
        if !on[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        let mut component = vec![start];
        let mut next = 0;
        while next < component.len() {
            let p = component[next];
            next += 1;
            for q in neighbours_8(p, w, h) {
                if on[q] && !seen[q] && joined(p, q) {
                    seen[q] = true;
                    component.push(q);
                }
            }
        }
        component.sort_unstable();
        out.push(component);
    }
    out
}

/// The instance an [`UNSURE`] pixel `p` of a w×h proposal map is counted to when the mask
/// losses claim the proposals' soft edges (`colf-train --mask-claim`): the nearest instance
/// pixel within `radius` pixels (Chebyshev distance; within one distance the first in row-major
/// order). None for a pixel that is not unsure or has no instance that near. An edge ring is
/// mostly the object's own antialiased outline, and an object's whole outline is what FG-ARI
/// scores (all or nothing for a lone object, `metrics::fg_ari`).
pub fn claimed_instance(ids: &[u8], w: usize, h: usize, p: usize, radius: usize) -> Option<u8> {
    if ids[p] != UNSURE {
        return None;
    }
    let (x, y) = ((p % w) as isize, (p / w) as isize);
    for r in 1..=radius as isize {
        for yy in (y - r).max(0)..=(y + r).min(h as isize - 1) {
            // Only the pixels at Chebyshev distance exactly r: the square's rows at ±r whole,
            // the rows between only at their two ends.
            let whole_row = (yy - y).abs() == r;
            let step = if whole_row { 1 } else { 2 * r as usize };
            for xx in ((x - r)..=(x + r)).step_by(step) {
                if xx < 0 || xx >= w as isize {
                    continue;
                }
                let id = ids[yy as usize * w + xx as usize];
                if is_instance(id) {
                    return Some(id);
                }
            }
        }
    }
    None
}

/// `ids` with every [`UNSURE`] pixel within `radius` of an instance counted to it
/// ([`claimed_instance`]).
pub fn claim_edges(ids: &[u8], w: usize, h: usize, radius: usize) -> Vec<u8> {
    (0..ids.len())
        .map(|p| claimed_instance(ids, w, h, p, radius).unwrap_or(ids[p]))
        .collect()
}

/// Whether `hit` holds for some pixel within `radius` pixels (Chebyshev distance) of pixel `p`
/// of a w×h grid, `p` included.
pub fn any_within(
    w: usize,
    h: usize,
    p: usize,
    radius: usize,
    hit: impl Fn(usize) -> bool,
) -> bool {
    let (x, y) = (p % w, p / w);
    let (x0, x1) = (x.saturating_sub(radius), (x + radius).min(w - 1));
    let (y0, y1) = (y.saturating_sub(radius), (y + radius).min(h - 1));
    (y0..=y1).any(|yy| (x0..=x1).any(|xx| hit(yy * w + xx)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(w: u32, h: u32, f: impl Fn(usize, usize) -> [f32; 3]) -> RgbImage32 {
        let data = (0..(w * h) as usize)
            .flat_map(|p| f(p % w as usize, p / w as usize))
            .collect();
        RgbImage32 { w, h, data }
    }

    /// A 32×32 floor with a brightness gradient, a red square, a blue square touching nothing,
    /// a grey shadow (the floor × 0.6), a bright spot (× 1.4) and a one-pixel speck.
    fn scene() -> RgbImage32 {
        image(32, 32, |x, y| {
            let floor = 0.4 + 0.3 * y as f32 / 31.0 + 0.05 * x as f32 / 31.0;
            if (4..10).contains(&x) && (4..10).contains(&y) {
                [0.8, 0.1, 0.1]
            } else if (20..24).contains(&x) && (18..24).contains(&y) {
                [0.1, 0.2, 0.9]
            } else if (4..12).contains(&x) && (20..26).contains(&y) {
                [floor * 0.6; 3]
            } else if (26..30).contains(&x) && (26..30).contains(&y) {
                [(floor * 1.4).min(1.0); 3]
            } else if (x, y) == (28, 4) {
                [0.0, 1.0, 0.0]
            } else {
                [floor; 3]
            }
        })
    }

    /// Against a known background: a different hue is an object, the same hue darker or
    /// brighter (a blurred edge, a shadow) is unsure, the background itself is background.
    #[test]
    fn proposals_against_a_known_background() {
        let (w, h) = (20usize, 12usize);
        // A grey street with a brightness ramp.
        let background: Vec<f32> = (0..w * h)
            .flat_map(|p| {
                let v = 0.35 + 0.3 * (p % w) as f32 / w as f32;
                [v, v, v * 1.05]
            })
            .collect();
        let mut data = background.clone();
        for y in 3..7 {
            for x in 2..6 {
                data[3 * (y * w + x)..3 * (y * w + x) + 3].copy_from_slice(&[0.2, 0.3, 0.8]);
            }
            for x in 12..15 {
                for c in 0..3 {
                    data[3 * (y * w + x) + c] *= 0.6;
                }
            }
        }
        let image = RgbImage32 {
            w: w as u32,
            h: h as u32,
            data,
        };
        let params = ProposalParams {
            threshold: 0.1,
            ring: 0,
            ..ProposalParams::default()
        };
        let ids = propose_against(&image, &background, 0.03, &params).unwrap();
        for y in 0..h {
            for x in 0..w {
                let want = if (3..7).contains(&y) && (2..6).contains(&x) {
                    1
                } else if (3..7).contains(&y) && (12..15).contains(&x) {
                    UNSURE
                } else {
                    0
                };
                assert_eq!(ids[y * w + x], want, "({x}, {y})");
            }
        }
        assert!(propose_against(&image, &background[3..], 0.03, &params).is_err());
    }

    #[test]
    fn the_background_fit_recovers_a_smooth_floor_under_objects() {
        let img = scene();
        let fitted = fit_background(&img, 3, 5);
        // Under the red square the fit is the floor, not the square's colour.
        let p = 6 * 32 + 6;
        let floor = 0.4 + 0.3 * 6.0 / 31.0 + 0.05 * 6.0 / 31.0;
        for c in 0..3 {
            assert!(
                (fitted[3 * p + c] - floor).abs() < 0.01,
                "{}",
                fitted[3 * p + c]
            );
        }
    }

    #[test]
    fn objects_become_instances_largest_first_and_shadows_unsure() {
        let ids = propose(&scene(), &ProposalParams::default());
        let at = |x: usize, y: usize| ids[y * 32 + x];
        assert_eq!(at(6, 6), 1, "the red square (36 px) is the largest");
        assert_eq!(at(21, 20), 2, "the blue square (24 px)");
        assert_eq!(at(8, 23), UNSURE, "the shadow");
        assert_eq!(at(27, 27), UNSURE, "a bright spot of the floor");
        assert_eq!(
            at(28, 4),
            UNSURE,
            "a one-pixel speck is too small to be an instance"
        );
        assert_eq!(at(10, 6), UNSURE, "the ring around an instance");
        assert_eq!(at(16, 14), 0, "open floor");
        assert_eq!(at(0, 31), 0);
    }

    /// The rows above which every pixel is wall in [`room`].
    const WALL: usize = 8;

    /// A 48×48 room seen towards a corner: two grey walls (brighter to the left) whose foot
    /// drops from row `WALL` at the view's sides to row 16 in the middle, a brown floor (a wood
    /// grain of up to ±`grain` in 2-pixel stripes) and a blue chair-sized block on it.
    fn room(grain: f32) -> RgbImage32 {
        room_with(grain, [0.1, 0.2, 0.8])
    }

    /// [`room`] with a block of colour `block`.
    fn room_with(grain: f32, block: [f32; 3]) -> RgbImage32 {
        image(48, 48, |x, y| {
            if y < 16 - x.abs_diff(24) / 3 {
                [0.7 - 0.004 * x as f32; 3]
            } else if (20..28).contains(&x) && (26..36).contains(&y) {
                block
            } else {
                let g = grain * [1.0, 0.3, -0.3, -1.0][(x / 2 + y) % 4];
                [0.5 + g, 0.3 + 0.3 * g, 0.2]
            }
        })
    }

    #[test]
    fn a_wall_is_a_surface_of_its_own_not_an_object() {
        let img = room(0.0);
        let ids = propose(&img, &ProposalParams::default());
        assert_eq!(ids[30 * 48 + 23], 1, "the block is the one instance");
        assert!(ids.iter().all(|&id| id == 0 || id == 1 || id == UNSURE));
        let wall_background = (0..WALL * 48).filter(|&p| ids[p] == 0).count();
        assert!(wall_background > WALL * 48 * 9 / 10, "{wall_background}");
        let flat = ProposalParams {
            layers: 0,
            ..ProposalParams::default()
        };
        // Without it the floor's polynomial bends towards the wall and leaves a band of
        // instances and unsure pixels along it.
        let wall_background_flat = propose(&img, &flat)[..WALL * 48]
            .iter()
            .filter(|&&id| id == 0)
            .count();
        assert!(
            wall_background_flat < wall_background,
            "{wall_background_flat}"
        );
        assert!(propose(&img, &flat)
            .iter()
            .any(|&id| id > 1 && is_instance(id)));
    }

    #[test]
    fn wood_grain_is_unsure_not_objects() {
        let img = room(0.1);
        let ids = propose(&img, &ProposalParams::default());
        assert_eq!(ids[30 * 48 + 23], 1, "the block is the one instance");
        assert!(ids.iter().all(|&id| id == 0 || id == 1 || id == UNSURE));
        let smooth = ProposalParams {
            texture: 0.0,
            ..ProposalParams::default()
        };
        let grain_instances = propose(&img, &smooth)
            .iter()
            .enumerate()
            .filter(|&(p, &id)| p >= WALL * 48 && is_instance(id) && img.data[3 * p + 2] < 0.5)
            .count();
        assert!(grain_instances > 0);
    }

    #[test]
    fn a_dim_block_of_another_hue_stands_out_from_the_grain() {
        // Within the grain's brightness tolerance, but mauve on brown wood.
        let img = room_with(0.1, [0.33, 0.3, 0.45]);
        let ids = propose(&img, &ProposalParams::default());
        assert_eq!(ids[30 * 48 + 23], 1, "the block is the one instance");
        let hue_blind = ProposalParams {
            hue_texture: f32::INFINITY,
            ..ProposalParams::default()
        };
        assert_eq!(propose(&img, &hue_blind)[30 * 48 + 23], UNSURE);
    }

    #[test]
    fn a_plain_or_tiny_image_has_no_instances() {
        let flat = image(16, 16, |_, _| [0.5, 0.5, 0.5]);
        assert!(propose(&flat, &ProposalParams::default())
            .iter()
            .all(|&id| id == 0));
        let one = image(1, 1, |_, _| [0.2, 0.9, 0.1]);
        assert_eq!(propose(&one, &ProposalParams::default()).len(), 1);
        let empty = RgbImage32 {
            w: 0,
            h: 0,
            data: vec![],
        };
        assert!(propose(&empty, &ProposalParams::default()).is_empty());
    }

    #[test]
    fn scores_compare_instances_with_the_truth() {
        // Truth: objects 1 and 2. Proposals merge them into instance 1, call one object pixel
        // background, put an instance on a background pixel and leave one pixel unsure.
        let truth = [1u8, 1, 2, 2, 0, 0, 0, 2];
        let ids = [1u8, 1, 1, 1, 1, 0, UNSURE, 0];
        let s = score(&ids, &truth).unwrap();
        assert_eq!(
            s.fg_ari_on_instances,
            Some(0.0),
            "one instance over two objects"
        );
        assert!((s.objects_called_background - 0.2).abs() < 1e-12);
        assert_eq!(s.objects_unsure, 0.0);
        assert!((s.instances_on_background - 0.2).abs() < 1e-12);
        assert!((s.unsure - 0.125).abs() < 1e-12);
        let perfect = score(&truth, &truth).unwrap();
        assert_eq!(perfect.fg_ari, Some(1.0));
        assert!(score(&ids, &truth[..3]).is_err());
    }

    /// An unsure pixel takes the nearest instance within the radius; background, instances and
    /// far unsure pixels keep their ids.
    #[test]
    fn unsure_edges_are_claimed_by_the_nearest_instance() {
        // 5×3: instance 1 at (0, 1), instance 2 at (4, 1); unsure pixels between and a row of
        // background and unsure pixels above.
        #[rustfmt::skip]
        let ids = [
            0, UNSURE, 0, UNSURE, UNSURE,
            1, UNSURE, UNSURE, UNSURE, 2,
            0, 0, 0, 0, 0,
        ];
        let claimed = claim_edges(&ids, 5, 3, 1);
        #[rustfmt::skip]
        let expected = [
            0, 1, 0, 2, 2,
            1, 1, UNSURE, 2, 2,
            0, 0, 0, 0, 0,
        ];
        assert_eq!(claimed, expected);
        // Within two pixels the middle one is claimed too: both instances are 2 away, and the
        // first in row-major order (same row: the left one) wins.
        assert_eq!(claimed_instance(&ids, 5, 3, 7, 2), Some(1));
        assert_eq!(claim_edges(&ids, 5, 3, 0), ids.to_vec());
        // Corners of the grid: no index leaves it.
        let lone = [UNSURE; 4];
        assert_eq!(claim_edges(&lone, 2, 2, 3), lone.to_vec());
    }

    #[test]
    fn components_are_8_connected() {
        // Two diagonal pixels touch; a third pixel apart does not.
        let mut on = vec![false; 16];
        on[0] = true;
        on[5] = true;
        on[15] = true;
        let c = components_8(&on, 4, 4, |_, _| true);
        assert_eq!(c, vec![vec![0, 5], vec![15]]);
        // A join condition splits them.
        let c = components_8(&on, 4, 4, |_, _| false);
        assert_eq!(c, vec![vec![0], vec![5], vec![15]]);
    }

    #[test]
    fn fragments_join_the_neighbour_with_the_longest_border() {
        // 4×2: a (pixels 0, 1, 4, 5), a one-pixel fragment (2) touching a on two pixels and b
        // (3, 7) on two as well, ties go to the lower index; a fragment with no neighbour stays.
        let merged = merge_fragments(vec![vec![0, 1, 4, 5], vec![2], vec![3, 7]], 4, 2, 2);
        assert_eq!(merged, vec![vec![0, 1, 2, 4, 5], vec![3, 7]]);
        let alone = merge_fragments(vec![vec![0], vec![7]], 4, 2, 5);
        assert_eq!(alone, vec![vec![0], vec![7]]);
    }

    #[test]
    fn singular_systems_fall_back_to_none() {
        assert_eq!(solve(vec![1.0, 2.0, 2.0, 4.0], vec![1.0, 2.0], 2), None);
        let x = solve(vec![2.0, 0.0, 0.0, 4.0], vec![2.0, 8.0], 2).unwrap();
        assert_eq!(x, vec![1.0, 2.0]);
    }
}
