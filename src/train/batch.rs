//! Training batches: for each scene, the input views to encode (one random view, or the scene's
//! context views: the paper's City-Block encodes a view in front of each row of cars) and rays
//! sampled from the input views and novel views to supervise (the authors supervised only the
//! input view by default — a known trap: a decoder that only ever reconstructs the view it was
//! given need not learn 3D).

use crate::dataset::SceneData;
use crate::proposals::{any_within, claimed_instance, is_instance, UNSURE};
use anyhow::{bail, Result};
use glam::DVec3;
use rand::rngs::StdRng;
use rand::Rng;

/// How views and rays are drawn.
#[derive(Clone, Debug)]
pub struct RaySampling {
    /// Views supervised per scene: the input views plus `views - (input views)` others.
    pub views: usize,
    /// The views every scene encodes (its context views), in this order; empty: one random view.
    pub context_views: Vec<usize>,
    /// Rays per supervised view.
    pub rays_per_view: usize,
    /// Share of each view's rays drawn from ground-truth object pixels (needs masks; 0 = uniform).
    pub object_fraction: f64,
    /// Background pixels within this many pixels of an object are marked `near_object`.
    pub mask_margin: usize,
    /// An unsure proposal pixel within this many pixels of an instance counts as that
    /// instance ([`claimed_instance`]; 0 = off).
    pub mask_claim: usize,
    /// With > 0, background pixels darker than their view's floor by more than this (sRGB
    /// brightness in [0, 1]) are marked `near_object` too: the shadows objects cast.
    pub shadow_depth: f64,
}

/// The brightness below which a background pixel of this view counts as shadow: the median
/// brightness (mean of R, G, B) of its background pixels — mostly lit floor — minus `depth`.
/// None when `depth` is 0 or the view has no background.
pub fn shadow_threshold(mask: &[u8], image: &[f32], depth: f64) -> Option<f32> {
    if depth <= 0.0 {
        return None;
    }
    let mut background: Vec<f32> = (0..mask.len())
        .filter(|&p| mask[p] == 0)
        .map(|p| brightness(image, p))
        .collect();
    if background.is_empty() {
        return None;
    }
    let middle = background.len() / 2;
    let (_, median, _) = background.select_nth_unstable_by(middle, f32::total_cmp);
    Some(*median - depth as f32)
}

fn brightness(image: &[f32], p: usize) -> f32 {
    (image[3 * p] + image[3 * p + 1] + image[3 * p + 2]) / 3.0
}

/// Which pixels of one view the mask losses leave to the colour loss: background pixels within
/// `margin` pixels of an object (see [`near_object`]) and, with a `shadow_below` threshold
/// ([`shadow_threshold`]), background pixels darker than it.
pub struct MaskExclusion<'a> {
    /// Object ids, w×h (0 = background).
    pub mask: &'a [u8],
    /// The view's image, sRGB, h×w×3.
    pub image: &'a [f32],
    pub w: usize,
    pub h: usize,
    pub margin: usize,
    pub shadow_below: Option<f32>,
}

impl MaskExclusion<'_> {
    /// Whether the mask losses leave pixel (x, y) to the colour loss: an [`UNSURE`] pixel of
    /// a proposal, or a background pixel in an object's band or shadow.
    pub fn leaves(&self, x: usize, y: usize) -> bool {
        let p = y * self.w + x;
        self.mask[p] == UNSURE
            || self.mask[p] == 0
                && (self
                    .shadow_below
                    .is_some_and(|t| brightness(self.image, p) < t)
                    || near_object(self.mask, self.w, self.h, x, y, self.margin))
    }
}

/// Whether pixel (x, y) of a w×h id mask is background with an object pixel within `margin`
/// pixels (Chebyshev distance).
pub fn near_object(mask: &[u8], w: usize, h: usize, x: usize, y: usize, margin: usize) -> bool {
    if margin == 0 || mask[y * w + x] != 0 {
        return false;
    }
    any_within(w, h, y * w + x, margin, |q| mask[q] != 0)
}

/// An encoded view of a scene's sample: the image the encoder reads, and the camera its slots
/// are placed from.
pub struct InputView {
    /// sRGB [0, 1], h×w×3.
    pub image: Vec<f32>,
    pub h: usize,
    pub w: usize,
    /// Object ids per pixel (0 = background), when the data has masks.
    pub mask: Option<Vec<u8>>,
    /// The view's camera (its slots' frames are placed from it).
    pub frame: crate::camera::Frame,
    /// The view's shadow threshold (`RaySampling::shadow_depth`; None when off).
    pub shadow_below: Option<f32>,
}

/// One scene's part of a batch.
pub struct SceneSample {
    /// The views encoded: one, or the context views; their slots together are the scene's.
    pub inputs: Vec<InputView>,
    pub origins: Vec<DVec3>,
    pub dirs: Vec<DVec3>,
    /// Target colours, R×3.
    pub targets: Vec<f32>,
    /// Ground-truth object id per ray (0 = background; all 0 without masks).
    pub ids: Vec<u8>,
    /// Per ray: a background pixel within `RaySampling::mask_margin` pixels of an object (the
    /// band where objects cast shadows) or in shadow (`RaySampling::shadow_depth`); mask losses
    /// leave it to the colour loss.
    pub near_object: Vec<bool>,
    pub has_masks: bool,
    /// Some(rays per view) when `ids` are local to each view (object proposals): objects are
    /// then matched to slots view by view, in blocks of that many rays.
    pub view_block: Option<usize>,
}

/// Draws a sample of `scene` with `rng`.
pub fn sample_scene(
    scene: &SceneData,
    sampling: &RaySampling,
    rng: &mut StdRng,
) -> Result<SceneSample> {
    let n_views = scene.views.len();
    if n_views == 0 {
        bail!("scene {} has no views", scene.name);
    }
    let inputs = if sampling.context_views.is_empty() {
        vec![rng.random_range(0..n_views)]
    } else {
        if let Some(&v) = sampling.context_views.iter().find(|&&v| v >= n_views) {
            bail!(
                "scene {} has {n_views} views; there is no context view {v}",
                scene.name
            );
        }
        sampling.context_views.clone()
    };
    // The input views first, then distinct other views (with repeats only if there are too few).
    let mut others: Vec<usize> = (0..n_views).filter(|v| !inputs.contains(v)).collect();
    let mut views: Vec<usize> = inputs.iter().copied().take(sampling.views).collect();
    while views.len() < sampling.views {
        if others.is_empty() {
            others = (0..n_views).collect();
        }
        let pick = rng.random_range(0..others.len());
        views.push(others.swap_remove(pick));
    }
    let has_masks = scene.views.iter().all(|v| v.mask.is_some());
    let total = sampling.views * sampling.rays_per_view;
    let mut sample = SceneSample {
        inputs: inputs
            .iter()
            .map(|&v| {
                let view = &scene.views[v];
                InputView {
                    image: view.image.data.clone(),
                    h: view.image.h as usize,
                    w: view.image.w as usize,
                    mask: view.mask.clone(),
                    frame: view.frame.clone(),
                    // Set below, where the supervised views' thresholds are computed.
                    shadow_below: None,
                }
            })
            .collect(),
        origins: Vec::with_capacity(total),
        dirs: Vec::with_capacity(total),
        targets: Vec::with_capacity(3 * total),
        ids: Vec::with_capacity(total),
        near_object: Vec::with_capacity(total),
        has_masks,
        view_block: scene.view_local_ids.then_some(sampling.rays_per_view),
    };
    for &v in &views {
        let view = &scene.views[v];
        let (w, h) = (view.image.w as usize, view.image.h as usize);
        let object_pixels: Vec<usize> = match (&view.mask, sampling.object_fraction > 0.0) {
            (Some(mask), true) => (0..w * h).filter(|&p| is_instance(mask[p])).collect(),
            _ => Vec::new(),
        };
        let n_object = if object_pixels.is_empty() {
            0
        } else {
            (sampling.object_fraction * sampling.rays_per_view as f64).round() as usize
        };
        let exclusion = view.mask.as_ref().map(|mask| MaskExclusion {
            mask,
            image: &view.image.data,
            w,
            h,
            margin: sampling.mask_margin,
            shadow_below: shadow_threshold(mask, &view.image.data, sampling.shadow_depth),
        });
        if let Some(i) = inputs.iter().position(|&input| input == v) {
            sample.inputs[i].shadow_below = exclusion.as_ref().and_then(|e| e.shadow_below);
        }
        for r in 0..sampling.rays_per_view {
            let p = if r < n_object {
                object_pixels[rng.random_range(0..object_pixels.len())]
            } else {
                rng.random_range(0..w * h)
            };
            let (i, j) = ((p % w) as u32, (p / w) as u32);
            let ray = view.frame.pixel_ray(i, j);
            sample.origins.push(ray.origin);
            sample.dirs.push(ray.direction);
            sample
                .targets
                .extend_from_slice(&view.image.data[3 * p..3 * p + 3]);
            let claimed = view
                .mask
                .as_ref()
                .and_then(|m| claimed_instance(m, w, h, p, sampling.mask_claim));
            sample
                .ids
                .push(claimed.unwrap_or_else(|| view.mask.as_ref().map_or(0, |m| m[p])));
            sample.near_object.push(
                claimed.is_none()
                    && exclusion
                        .as_ref()
                        .is_some_and(|e| e.leaves(i as usize, j as usize)),
            );
        }
    }
    Ok(sample)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// A scene of `n` 2×2 views, view v filled with the grey v / 10.
    fn scene_of(n: usize) -> SceneData {
        let views = (0..n)
            .map(|v| crate::dataset::View {
                path: format!("view_{v}.png").into(),
                image: crate::image_io::RgbImage32 {
                    w: 2,
                    h: 2,
                    data: vec![v as f32 / 10.0; 12],
                },
                mask: Some(vec![0, 1, 0, 0]),
                frame: crate::encode::default_camera(2, 2),
            })
            .collect();
        SceneData {
            name: "s".into(),
            views,
            view_local_ids: true,
        }
    }

    /// The view each of `sample`'s rays came from (their targets are the views' greys).
    fn ray_views(sample: &SceneSample) -> Vec<usize> {
        sample
            .targets
            .chunks(3)
            .map(|c| (c[0] * 10.0).round() as usize)
            .collect()
    }

    #[test]
    fn context_views_are_encoded_together_and_supervised_first() {
        let scene = scene_of(5);
        let sampling = |views, context_views: &[usize]| RaySampling {
            views,
            context_views: context_views.to_vec(),
            rays_per_view: 3,
            object_fraction: 0.0,
            mask_margin: 0,
            mask_claim: 0,
            shadow_depth: 0.0,
        };
        for seed in 0..8 {
            let mut rng = StdRng::seed_from_u64(seed);
            let sample = sample_scene(&scene, &sampling(4, &[3, 1]), &mut rng).unwrap();
            let inputs: Vec<usize> = sample
                .inputs
                .iter()
                .map(|v| (v.image[0] * 10.0).round() as usize)
                .collect();
            assert_eq!(inputs, [3, 1]);
            assert!(sample.inputs.iter().all(|v| (v.w, v.h) == (2, 2)));
            let rays = ray_views(&sample);
            assert_eq!(&rays[..6], &[3, 3, 3, 1, 1, 1]);
            // Then two distinct views that are not context views.
            let (a, b) = (rays[6], rays[9]);
            assert!(a != b && ![3, 1].contains(&a) && ![3, 1].contains(&b));
            assert!(rays[6..9].iter().all(|&v| v == a) && rays[9..].iter().all(|&v| v == b));
        }
        // Without context views, one random input view, supervised first.
        let mut rng = StdRng::seed_from_u64(3);
        let sample = sample_scene(&scene, &sampling(2, &[]), &mut rng).unwrap();
        assert_eq!(sample.inputs.len(), 1);
        let input = (sample.inputs[0].image[0] * 10.0).round() as usize;
        assert_eq!(ray_views(&sample)[0], input);
        // A context view the scene does not have: one error naming the scene and the view.
        let mut rng = StdRng::seed_from_u64(0);
        let error = sample_scene(&scene, &sampling(2, &[0, 5]), &mut rng)
            .err()
            .unwrap()
            .to_string();
        assert!(
            error.contains("scene s") && error.contains("context view 5"),
            "{error}"
        );
    }

    /// With a claim radius, rays on an unsure pixel next to an instance carry its id and are
    /// supervised; without, they are left to the colour loss.
    #[test]
    fn claimed_edges_are_supervised_as_their_instance() {
        let mut scene = scene_of(1);
        scene.views[0].mask = Some(vec![0, 1, UNSURE, UNSURE]);
        scene.views[0].image = crate::image_io::RgbImage32 {
            w: 4,
            h: 1,
            data: vec![0.5; 12],
        };
        scene.views[0].frame = crate::encode::default_camera(4, 1);
        let rays = |claim| {
            let sampling = RaySampling {
                views: 1,
                context_views: vec![0],
                rays_per_view: 64,
                object_fraction: 0.0,
                mask_margin: 0,
                mask_claim: claim,
                shadow_depth: 0.0,
            };
            let mut rng = StdRng::seed_from_u64(5);
            let sample = sample_scene(&scene, &sampling, &mut rng).unwrap();
            // The pixel each ray went through, from its direction's x (left to right).
            let mut xs: Vec<f64> = sample.dirs.iter().map(|d| d.x).collect();
            xs.sort_by(f64::total_cmp);
            xs.dedup();
            assert_eq!(xs.len(), 4, "every pixel drawn");
            let mut by_pixel = std::collections::BTreeMap::new();
            for ((d, &id), &near) in sample.dirs.iter().zip(&sample.ids).zip(&sample.near_object) {
                let x = xs.iter().position(|&v| v == d.x).unwrap();
                by_pixel.insert(x, (id, near));
            }
            by_pixel.into_values().collect::<Vec<_>>()
        };
        assert_eq!(
            rays(0),
            [(0, false), (1, false), (UNSURE, true), (UNSURE, true)]
        );
        assert_eq!(
            rays(1),
            [(0, false), (1, false), (1, false), (UNSURE, true)]
        );
        assert_eq!(rays(2), [(0, false), (1, false), (1, false), (1, false)]);
    }

    #[test]
    fn near_object_marks_the_background_band_around_objects() {
        // 5×1 mask with an object at x = 2.
        let mask = [0u8, 0, 4, 0, 0];
        let near: Vec<bool> = (0..5).map(|x| near_object(&mask, 5, 1, x, 0, 1)).collect();
        assert_eq!(near, vec![false, true, false, true, false]);
        let wide: Vec<bool> = (0..5).map(|x| near_object(&mask, 5, 1, x, 0, 2)).collect();
        assert_eq!(wide, vec![true, true, false, true, true]);
        assert!((0..5).all(|x| !near_object(&mask, 5, 1, x, 0, 0)));
    }

    #[test]
    fn unsure_proposal_pixels_are_left_to_the_colour_loss() {
        let mask = [0u8, 1, UNSURE, 0];
        let image = [0.5f32; 12];
        let exclusion = MaskExclusion {
            mask: &mask,
            image: &image,
            w: 4,
            h: 1,
            margin: 0,
            shadow_below: None,
        };
        let left: Vec<bool> = (0..4).map(|x| exclusion.leaves(x, 0)).collect();
        assert_eq!(left, vec![false, false, true, false]);
    }

    #[test]
    fn shadows_are_background_pixels_darker_than_the_floor() {
        // 6×1: floor 0.7, an object (id 2, dark), a shadow 0.45, floor, a slightly dark floor 0.66.
        let mask = [0u8, 0, 2, 0, 0, 0];
        let grey = |v: f32| [v, v, v];
        let image: Vec<f32> = [0.7, 0.7, 0.1, 0.45, 0.7, 0.66]
            .into_iter()
            .flat_map(grey)
            .collect();
        assert_eq!(shadow_threshold(&mask, &image, 0.0), None);
        let below = shadow_threshold(&mask, &image, 0.1);
        assert!((below.unwrap() - 0.6).abs() < 1e-6);
        let exclusion = |margin| MaskExclusion {
            mask: &mask,
            image: &image,
            w: 6,
            h: 1,
            margin,
            shadow_below: below,
        };
        let left: Vec<bool> = (0..6).map(|x| exclusion(0).leaves(x, 0)).collect();
        assert_eq!(left, vec![false, false, false, true, false, false]);
        // With a margin as well, the band around the object joins.
        let left: Vec<bool> = (0..6).map(|x| exclusion(1).leaves(x, 0)).collect();
        assert_eq!(left, vec![false, true, false, true, false, false]);
    }
}
