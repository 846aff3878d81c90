//! The fast renderer (`colf::render::fast`) against the candle path (`Colf::render_rays`): the
//! same weights must give the same colours, weights and ordering values within 1e-4, for the
//! light-field presets (with and without Fourier features) and the volumetric baseline; and the
//! fast renderer must be deterministic.

use colf::model::{Colf, Config, RayOutput};
use colf::render::fast::FastRenderer;
use glam::{DMat4, DQuat, DVec3};

fn noise(n: usize, seed: u64) -> Vec<f32> {
    let mut x = seed.wrapping_mul(0x9E3779B97F4A7C15) | 1;
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            ((x >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        })
        .collect()
}

/// `n` rays from a camera 12.4 units away towards the origin region; K slot frames scattered.
fn scene(k: usize, n: usize) -> (Vec<DMat4>, Vec<DVec3>, Vec<DVec3>) {
    let frames = (0..k)
        .map(|i| {
            let a = i as f64 * 2.399;
            DMat4::from_rotation_translation(
                DQuat::from_rotation_z(a),
                DVec3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.3 * i as f64),
            )
        })
        .collect();
    let eye = DVec3::new(8.0, -7.0, 7.9);
    let jitter = noise(3 * n, 99);
    let dirs = (0..n)
        .map(|i| {
            let t = DVec3::new(
                3.0 * jitter[3 * i] as f64,
                3.0 * jitter[3 * i + 1] as f64,
                jitter[3 * i + 2] as f64,
            );
            t - eye
        })
        .collect();
    (frames, vec![eye; n], dirs)
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn compare(cfg: &Config, k: usize, rays: usize, tol_order: f32) {
    compare_model(&Colf::init(cfg, 3).unwrap(), k, rays, tol_order);
}

fn compare_model(model: &Colf, k: usize, rays: usize, tol_order: f32) {
    compare_on(model, scene(k, rays), tol_order);
}

/// [`scene`] with some rays that miss the floor: every third looks up, every seventh runs
/// level (the floor features are zero on them, written over whatever the scratch held).
fn scene_with_sky(k: usize, n: usize) -> (Vec<DMat4>, Vec<DVec3>, Vec<DVec3>) {
    let (frames, origins, mut dirs) = scene(k, n);
    for (i, d) in dirs.iter_mut().enumerate() {
        if i % 3 == 1 {
            d.z = -d.z;
        } else if i % 7 == 5 {
            d.z = 0.0;
        }
    }
    (frames, origins, dirs)
}

fn compare_on(
    model: &Colf,
    (frames, origins, dirs): (Vec<DMat4>, Vec<DVec3>, Vec<DVec3>),
    tol_order: f32,
) {
    let cfg = model.config();
    let (k, rays) = (frames.len(), origins.len());
    let d = cfg.slot_dim;
    let latents: Vec<Vec<f32>> = (0..k).map(|i| noise(d, 10 + i as u64)).collect();
    let bg = noise(d, 7);
    let prepared = model.prepare(&latents, &bg).unwrap();
    let slow = model
        .render_rays(&prepared, &frames, &origins, &dirs)
        .unwrap();
    let fast_r = FastRenderer::new(model, &prepared, &frames).unwrap();
    let fast = fast_r.render(&origins, &dirs, None, None).unwrap();
    assert_eq!(fast.fields, 1 + k);
    let drgb = max_diff(&slow.rgb, &fast.rgb);
    let dw = max_diff(&slow.weights, &fast.weights);
    let dord = max_diff(&slow.ordering, &fast.ordering);
    eprintln!(
        "{} K={k}: max |Δ| rgb {drgb:.2e}, weights {dw:.2e}, ordering {dord:.2e}",
        cfg.preset
    );
    let dsh = max_diff(&slow.shadow, &fast.shadow);
    assert!(
        drgb < 1e-4 && dw < 1e-4 && dsh < 1e-4,
        "rgb {drgb}, weights {dw}, shadow {dsh}"
    );
    // Ordering values are world distances (~10 units): 1e-4 relative.
    assert!(dord < tol_order, "ordering {dord}");
    // Deterministic: a second render gives the same bits.
    let again: RayOutput = fast_r.render(&origins, &dirs, None, None).unwrap();
    assert_eq!(again, fast);
    if cfg.is_volumetric() {
        return;
    }
    // An all-true mask is the exact render.
    let all = vec![true; rays * (1 + k)];
    assert_eq!(
        fast_r.render(&origins, &dirs, None, Some(&all)).unwrap(),
        fast
    );
}

#[test]
fn light_field_small_matches_candle() {
    compare(&Config::small(), 5, 700, 2e-3);
    compare(&Config::small(), 0, 300, 2e-3);
}

#[test]
fn light_field_paper_matches_candle() {
    compare(&Config::paper(), 3, 600, 2e-3);
}

#[test]
fn light_field_with_fourier_features_matches_candle() {
    let cfg = Config::small()
        .with_overrides(&["ray_fourier_freqs=4".into(), "head_hidden_layers=2".into()])
        .unwrap();
    compare(&cfg, 4, 513, 2e-3);
}

/// Floor features on the background (its extra input columns; zeros in the slots' rows, on the
/// shadow lines and on rays that miss the floor): the fast renderer, which encodes into a
/// reused scratch buffer, must write every floor column of every row. The fresh model's
/// generated weights on those columns are not zero, in the slots' fields too, so a stale
/// value anywhere changes a colour. Several chunks of rays, with and without Fourier features
/// and shadow lines.
#[test]
fn light_field_with_floor_features_matches_candle() {
    for extra in [
        &[][..],
        &[
            "ray_fourier_freqs=2",
            "shadow_head=true",
            "shadow_light=[30, 55]",
        ][..],
    ] {
        let mut overrides = vec!["floor_fourier_freqs=5".to_string()];
        overrides.extend(extra.iter().map(|s| s.to_string()));
        let cfg = Config::small().with_overrides(&overrides).unwrap();
        let mut model = Colf::init(&cfg, 3).unwrap();
        if cfg.shadow_head {
            // Shadows that read the features (a fresh head's weights are zero), as in
            // `light_field_with_shadows_matches_candle`: a stale shadow-line row shows.
            let w: Vec<f32> = noise(cfg.lfn_features, 5)
                .iter()
                .map(|v| 0.03 * v)
                .collect();
            let (dev, n) = (candle_core::Device::Cpu, cfg.lfn_features);
            let bias = candle_core::Tensor::new(&[-0.1f32], &dev).unwrap();
            let weight = candle_core::Tensor::from_vec(w, (1, n), &dev).unwrap();
            model = model.with_tensor("heads.shadow.bias", bias).unwrap();
            model = model.with_tensor("heads.shadow.weight", weight).unwrap();
        }
        // On one thread of a pool of its own, every chunk after the first reuses the scratch
        // (called from outside a pool, rayon may give each chunk a fresh one).
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        pool.install(|| {
            compare_on(&model, scene_with_sky(4, 1100), 2e-3);
            compare_on(&model, scene_with_sky(0, 300), 2e-3);
        });
    }
}

#[test]
fn light_field_with_a_locality_bound_matches_candle() {
    let cfg = Config::small()
        .with_overrides(&["fg_locality=2.0".into(), "ray_fourier_freqs=6".into()])
        .unwrap();
    compare(&cfg, 6, 400, 2e-3);
}

#[test]
fn light_field_with_shadows_matches_candle() {
    // Shadows read on the rays themselves, and on their shadow lines toward a light.
    for light in [None, Some("[30, 55]")] {
        let mut overrides = vec!["shadow_head=true".to_string()];
        overrides.extend(light.map(|l| format!("shadow_light={l}")));
        let cfg = Config::small().with_overrides(&overrides).unwrap();
        // Strong shadows (bias −0.1: σ = softplus(−1) ≈ 0.31 where w·f = 0), weights on the
        // features.
        let w: Vec<f32> = noise(cfg.lfn_features, 5)
            .iter()
            .map(|v| 0.03 * v)
            .collect();
        let model = Colf::init(&cfg, 3)
            .unwrap()
            .with_tensor(
                "heads.shadow.bias",
                candle_core::Tensor::new(&[-0.1f32], &candle_core::Device::Cpu).unwrap(),
            )
            .unwrap()
            .with_tensor(
                "heads.shadow.weight",
                candle_core::Tensor::from_vec(w, (1, cfg.lfn_features), &candle_core::Device::Cpu)
                    .unwrap(),
            )
            .unwrap();
        compare_model(&model, 4, 500, 2e-3);
        // The shadows are there: each foreground slot's σ on every ray that meets the ground
        // (all of them without a light), none for the background.
        let prepared = model
            .prepare(&[noise(64, 1), noise(64, 2)], &noise(64, 3))
            .unwrap();
        let (frames, origins, dirs) = scene(2, 50);
        // Every fifth ray looks up, away from the ground.
        let dirs: Vec<DVec3> = dirs
            .iter()
            .enumerate()
            .map(|(i, d)| {
                if i % 5 == 0 {
                    DVec3::new(d.x, d.y, 0.5)
                } else {
                    *d
                }
            })
            .collect();
        let mut renderer = FastRenderer::new(&model, &prepared, &frames).unwrap();
        let out = renderer.render(&origins, &dirs, None, None).unwrap();
        // Without the shadows: the same segmentation, no pixel darker, some brighter.
        renderer.drop_shadows();
        let bright = renderer.render(&origins, &dirs, None, None).unwrap();
        assert_eq!(bright.weights, out.weights);
        assert!(bright.shadow.iter().all(|&v| v == 0.0));
        assert!(bright.rgb.iter().zip(&out.rgb).all(|(b, o)| b >= o));
        assert!(bright.rgb.iter().zip(&out.rgb).any(|(b, o)| b > o));
        let slow = model
            .render_rays(&prepared, &frames, &origins, &dirs)
            .unwrap();
        assert!(max_diff(&slow.shadow, &out.shadow) < 1e-4);
        assert!(max_diff(&slow.rgb, &out.rgb) < 1e-4);
        for (row, (o, d)) in out.shadow.chunks_exact(3).zip(origins.iter().zip(&dirs)) {
            assert_eq!(row[0], 0.0);
            let meets_ground = o.z > 0.0 && d.z < 0.0;
            let cast = light.is_none() || meets_ground;
            assert_eq!(row[1] > 0.0 && row[2] > 0.0, cast, "{row:?}");
        }
    }
}

/// With the slots' own line scale (`slot_scale`), the fast renderer reads the slots' rays and
/// shadow lines as the training code does, and the render is not the one without it.
#[test]
fn light_field_with_a_slot_scale_matches_candle() {
    let overrides = |slot_scale: &str| -> Vec<String> {
        [
            "ray_fourier_freqs=6",
            "shadow_head=true",
            "shadow_light=[30, 55]",
            "shadow_reach=2.5",
            slot_scale,
        ]
        .map(String::from)
        .to_vec()
    };
    let scaled = Config::small()
        .with_overrides(&overrides("slot_scale=1.5"))
        .unwrap();
    compare(&scaled, 4, 500, 2e-3);
    let render = |cfg: &Config| {
        let model = Colf::init(cfg, 3).unwrap();
        let latents: Vec<Vec<f32>> = (0..4).map(|i| noise(64, 10 + i)).collect();
        let (frames, origins, dirs) = scene(4, 300);
        let prepared = model.prepare(&latents, &noise(64, 7)).unwrap();
        let renderer = FastRenderer::new(&model, &prepared, &frames).unwrap();
        renderer.render(&origins, &dirs, None, None).unwrap().rgb
    };
    let plain = Config::small()
        .with_overrides(&overrides("slot_scale=0"))
        .unwrap();
    assert!(max_diff(&render(&scaled), &render(&plain)) > 1e-3);
}

/// With `shadow_reach`, the fast renderer leaves out the same shadow lines as the training
/// code: the same render, and some ground rays without the shadow they had without a reach.
#[test]
fn light_field_with_a_shadow_reach_matches_candle() {
    let strong = |overrides: &[&str]| {
        let overrides: Vec<String> = overrides.iter().map(|s| s.to_string()).collect();
        let cfg = Config::small().with_overrides(&overrides).unwrap();
        let w: Vec<f32> = noise(cfg.lfn_features, 5)
            .iter()
            .map(|v| 0.03 * v)
            .collect();
        let dev = candle_core::Device::Cpu;
        Colf::init(&cfg, 3)
            .unwrap()
            .with_tensor(
                "heads.shadow.bias",
                candle_core::Tensor::new(&[-0.1f32], &dev).unwrap(),
            )
            .unwrap()
            .with_tensor(
                "heads.shadow.weight",
                candle_core::Tensor::from_vec(w, (1, cfg.lfn_features), &dev).unwrap(),
            )
            .unwrap()
    };
    let light = ["shadow_head=true", "shadow_light=[30, 55]"];
    let free = strong(&light);
    let bounded = strong(&[light[0], light[1], "shadow_reach=2.5"]);
    compare_model(&bounded, 4, 500, 2e-3);
    let latents: Vec<Vec<f32>> = (0..4).map(|i| noise(64, 10 + i)).collect();
    let (frames, origins, dirs) = scene(4, 500);
    let shadow = |model: &Colf| {
        let prepared = model.prepare(&latents, &noise(64, 7)).unwrap();
        let renderer = FastRenderer::new(model, &prepared, &frames).unwrap();
        renderer.render(&origins, &dirs, None, None).unwrap().shadow
    };
    let (all, near) = (shadow(&free), shadow(&bounded));
    let cut = near
        .iter()
        .zip(&all)
        .filter(|(n, a)| **n == 0.0 && **a > 0.0)
        .count();
    assert!(cut > 100, "{cut} shadow lines left out");
    for (n, a) in near.iter().zip(&all) {
        assert!(*n == 0.0 || n == a, "{n} vs {a}");
    }
}

/// A camera among the slots: with `cull_behind`, the slots more than that behind it along a ray
/// get no weight there, in the candle path and the fast renderer alike, and the rest of the
/// render is what the same scene without them gives.
#[test]
fn slots_behind_the_camera_are_culled_in_both_renderers() {
    let cfg = Config::small()
        .with_overrides(&[
            "background_from_nearest_slot=true".into(),
            "cull_behind=1.5".into(),
        ])
        .unwrap();
    let model = Colf::init(&cfg, 3).unwrap();
    let (mut frames, _, _) = scene(4, 1);
    // The camera stands at the scene's centre looking along +x; slot 4 sits 6 units behind it.
    frames.push(DMat4::from_translation(DVec3::new(-6.0, 0.0, 0.3)));
    let eye = DVec3::new(0.0, 0.0, 1.0);
    let jitter = noise(2 * 300, 5);
    let dirs: Vec<DVec3> = (0..300)
        .map(|i| {
            DVec3::new(
                1.0,
                0.6 * jitter[2 * i] as f64,
                0.4 * jitter[2 * i + 1] as f64 - 0.1,
            )
        })
        .collect();
    let origins = vec![eye; dirs.len()];
    let latents: Vec<Vec<f32>> = (0..5).map(|i| noise(cfg.slot_dim, 10 + i)).collect();
    let bg = noise(cfg.slot_dim, 7);
    let prepared = model.prepare(&latents, &bg).unwrap();
    let slow = model
        .render_rays(&prepared, &frames, &origins, &dirs)
        .unwrap();
    let fast = FastRenderer::new(&model, &prepared, &frames)
        .unwrap()
        .render(&origins, &dirs, None, None)
        .unwrap();
    assert!(max_diff(&slow.rgb, &fast.rgb) < 1e-4 && max_diff(&slow.weights, &fast.weights) < 1e-4);
    let fields = 1 + frames.len();
    let behind: f32 = fast
        .weights
        .chunks(fields)
        .map(|w| w[5])
        .fold(0.0, f32::max);
    assert!(
        behind < 1e-12,
        "the slot behind the camera still weighs {behind}"
    );
    // The same as the scene without that slot.
    let without = model.prepare(&latents[..4], &bg).unwrap();
    let rest = FastRenderer::new(&model, &without, &frames[..4])
        .unwrap()
        .render(&origins, &dirs, None, None)
        .unwrap();
    assert!(
        max_diff(&rest.rgb, &fast.rgb) < 1e-5,
        "{}",
        max_diff(&rest.rgb, &fast.rgb)
    );
    // Without the option it takes the rays it lies on.
    let plain = Colf::init(
        &Config::small()
            .with_overrides(&["background_from_nearest_slot=true".into()])
            .unwrap(),
        3,
    )
    .unwrap();
    let prepared = plain.prepare(&latents, &bg).unwrap();
    let drawn = FastRenderer::new(&plain, &prepared, &frames)
        .unwrap()
        .render(&origins, &dirs, None, None)
        .unwrap();
    let weight: f32 = drawn
        .weights
        .chunks(fields)
        .map(|w| w[5])
        .fold(0.0, f32::max);
    assert!(weight > 0.1, "{weight}");
}

#[test]
fn volumetric_matches_candle() {
    compare(&Config::volumetric(), 3, 40, 2e-3);
}

#[test]
fn masked_fields_get_no_weight_and_the_background_is_required() {
    let cfg = Config::small();
    let model = Colf::init(&cfg, 3).unwrap();
    let latents: Vec<Vec<f32>> = (0..3).map(|i| noise(64, i)).collect();
    let prepared = model.prepare(&latents, &noise(64, 9)).unwrap();
    let (frames, origins, dirs) = scene(3, 50);
    let r = FastRenderer::new(&model, &prepared, &frames).unwrap();
    let mut mask = vec![true; 50 * 4];
    for ray in 0..50 {
        mask[ray * 4 + 2] = ray % 2 == 0;
    }
    let out = r.render(&origins, &dirs, None, Some(&mask)).unwrap();
    for ray in 0..50 {
        let w = &out.weights[ray * 4..ray * 4 + 4];
        assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        if ray % 2 == 1 {
            assert_eq!(w[2], 0.0);
            assert_eq!(out.ordering[ray * 4 + 2], f32::INFINITY);
        } else {
            assert!(w[2] > 0.0);
        }
    }
    mask[0] = false;
    assert!(r.render(&origins, &dirs, None, Some(&mask)).is_err());
    assert!(r.render(&origins, &dirs, Some(32), None).is_err());
}

#[test]
fn subsets_composited_from_fields_evaluated_once_equal_masked_renders() {
    // Shadows along a light and Fourier features: every value the composition reads is kept;
    // 600 rays span three chunks, the last one short.
    let overrides = [
        "shadow_head=true",
        "shadow_light=[30, 55]",
        "ray_fourier_freqs=4",
    ]
    .map(String::from);
    let cfg = Config::small().with_overrides(&overrides).unwrap();
    let model = Colf::init(&cfg, 3).unwrap();
    let k = 4;
    let latents: Vec<Vec<f32>> = (0..k).map(|i| noise(cfg.slot_dim, 20 + i as u64)).collect();
    let prepared = model.prepare(&latents, &noise(cfg.slot_dim, 8)).unwrap();
    let (frames, origins, dirs) = scene(k, 600);
    let r = FastRenderer::new(&model, &prepared, &frames).unwrap();
    let values = r.evaluate_fields(&origins, &dirs).unwrap();
    for keep in [
        vec![true; k + 1],
        vec![true, false, true, true, true],
        vec![true, true, false, false, true],
        vec![true, false, false, false, false],
    ] {
        let mask = keep.repeat(origins.len());
        let rendered = r.render(&origins, &dirs, None, Some(&mask)).unwrap();
        let composited = r.composite(&values, &keep).unwrap();
        assert_eq!(rendered.rgb, composited.rgb, "{keep:?}");
        assert_eq!(rendered.weights, composited.weights, "{keep:?}");
        assert_eq!(rendered.shadow, composited.shadow, "{keep:?}");
        let same_ordering = rendered
            .ordering
            .iter()
            .zip(&composited.ordering)
            .all(|(a, b)| a == b || (a.is_infinite() && b.is_infinite()));
        assert!(same_ordering, "{keep:?}");
    }
    assert!(r
        .composite(&values, &[false, true, true, true, true])
        .is_err());
    assert!(r.composite(&values, &[true; 3]).is_err());
}

/// With `slot_reach`, the fast renderer leaves each slot out of the same rays as the training
/// code (weight 0, ordering +∞, no shadow): the same render, with shadows on lines and on the
/// ray, and through `evaluate_fields` + `composite`; a fair share of the (ray, slot) pairs is
/// left out, and an adaptive mask narrows further without bringing a slot back.
#[test]
fn light_field_with_a_slot_reach_matches_candle() {
    for extra in [
        &[
            "shadow_light=[30, 55]",
            "shadow_reach=2.5",
            "slot_reach=2.5",
        ][..],
        &["slot_reach=2"][..],
    ] {
        let mut overrides = vec!["shadow_head=true".to_string(), "ray_fourier_freqs=2".into()];
        overrides.extend(extra.iter().map(|s| s.to_string()));
        let cfg = Config::small().with_overrides(&overrides).unwrap();
        let model = Colf::init(&cfg, 3).unwrap();
        compare_model(&model, 4, 500, 2e-3);
        let latents: Vec<Vec<f32>> = (0..4).map(|i| noise(64, 10 + i)).collect();
        let (frames, origins, dirs) = scene(4, 500);
        let prepared = model.prepare(&latents, &noise(64, 7)).unwrap();
        let slow = model
            .render_rays(&prepared, &frames, &origins, &dirs)
            .unwrap();
        let renderer = FastRenderer::new(&model, &prepared, &frames).unwrap();
        let fast = renderer.render(&origins, &dirs, None, None).unwrap();
        let absent: Vec<usize> = (0..fast.ordering.len())
            .filter(|&u| fast.ordering[u] == f32::INFINITY)
            .collect();
        let share = absent.len() as f32 / (4.0 * 500.0);
        assert!((0.1..0.9).contains(&share), "{share} of the pairs absent");
        for &u in &absent {
            assert!(u % 5 != 0, "the background is always present");
            assert_eq!(slow.ordering[u], f32::INFINITY);
            assert_eq!((fast.weights[u], fast.shadow[u]), (0.0, 0.0));
        }
        let values = renderer.evaluate_fields(&origins, &dirs).unwrap();
        let all = renderer.composite(&values, &[true; 5]).unwrap();
        assert_eq!(all, fast);
        let some = renderer
            .composite(&values, &[true, true, false, true, true])
            .unwrap();
        let mask: Vec<bool> = (0..2500).map(|u| u % 5 != 2).collect();
        assert_eq!(
            some,
            renderer.render(&origins, &dirs, None, Some(&mask)).unwrap()
        );
    }
}

/// Reaches set on a renderer (as an encoding judges its tries and its redundant slots) render
/// exactly what the same weights render with the reaches in their config, and change the
/// render of a model without them.
#[test]
fn reaches_set_on_a_renderer_match_a_model_with_them() {
    let free = Colf::init(
        &Config::small()
            .with_overrides(&[
                "shadow_head=true".to_string(),
                "shadow_light=[30, 55]".into(),
                "ray_fourier_freqs=2".into(),
            ])
            .unwrap(),
        3,
    )
    .unwrap();
    let bounded = free
        .configured(&["shadow_reach=2.5".to_string(), "slot_reach=2".into()])
        .unwrap();
    let latents: Vec<Vec<f32>> = (0..4).map(|i| noise(64, 10 + i)).collect();
    let (frames, origins, dirs) = scene(4, 500);
    let render = |model: &Colf, reached: Option<&Config>| {
        let prepared = model.prepare(&latents, &noise(64, 7)).unwrap();
        let renderer = FastRenderer::new(model, &prepared, &frames)
            .unwrap()
            .within_reaches(reached);
        let values = renderer.evaluate_fields(&origins, &dirs).unwrap();
        (
            renderer.render(&origins, &dirs, None, None).unwrap(),
            renderer
                .composite(&values, &[true, false, true, true, true])
                .unwrap(),
        )
    };
    let exact = render(&bounded, None);
    assert_eq!(render(&free, Some(bounded.config())), exact);
    assert_ne!(render(&free, None), exact);
    // A model's own reaches give way to the ones set, none included.
    assert_eq!(render(&bounded, Some(free.config())), render(&free, None));
}
