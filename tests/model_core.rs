//! The COLF model: gradients reach every parameter, numerics survive extremes, slots in
//! different frames composite front to back, checkpoints are reproducible and validated.

use candle_core::{DType, Device, Tensor};
use colf::model::grow::{Growth, SlotValues};
use colf::model::{Colf, Config, RayBatch, SceneRays};
use glam::{DMat4, DVec3};
use proptest::prelude::*;
use rand::rngs::StdRng;
use rand::SeedableRng;

/// A tiny config so forward+backward is quick.
fn tiny() -> Config {
    Config {
        preset: "tiny".into(),
        encoder_size: 16,
        encoder_first_stride: 2,
        encoder_channels: 8,
        encoder_channels_low: 8,
        feature_dim: 8,
        slot_dim: 8,
        slot_iters: 3,
        slot_mlp_hidden: 16,
        default_slots: 2,
        lfn_hidden: 16,
        lfn_hidden_layers: 2,
        lfn_features: 8,
        ray_fourier_freqs: 1,
        hypernet_hidden: 8,
        head_hidden: 8,
        head_hidden_layers: 1,
        compositor_hidden: 8,
        compositor_hidden_layers: 1,
        scene_scale: 4.0,
        ..Config::small()
    }
}

/// Rays of a camera at `eye` looking at the origin, n×n pixels over a small field of view.
fn camera_rays(eye: DVec3, n: usize) -> (Vec<DVec3>, Vec<DVec3>) {
    let forward = (-eye).normalize();
    let up = if forward.z.abs() > 0.99 {
        DVec3::X
    } else {
        DVec3::Z
    };
    let right = forward.cross(up).normalize();
    let up = right.cross(forward);
    let mut origins = Vec::new();
    let mut dirs = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let u = (i as f64 + 0.5) / n as f64 - 0.5;
            let v = (j as f64 + 0.5) / n as f64 - 0.5;
            origins.push(eye);
            dirs.push(forward + 0.8 * (u * right - v * up));
        }
    }
    (origins, dirs)
}

fn test_image(n: usize) -> Vec<f32> {
    (0..n * n * 3)
        .map(|i| {
            let p = i / 3;
            let (x, y) = (p % n, p / n);
            let inside = (x as i64 - n as i64 / 2).pow(2) + (y as i64 - n as i64 / 3).pow(2)
                < (n as i64 / 5).pow(2);
            if inside {
                [0.9, 0.2, 0.1][i % 3]
            } else {
                0.5
            }
        })
        .collect()
}

fn all_finite(v: &[f32]) -> bool {
    v.iter().all(|x| x.is_finite())
}

#[test]
fn every_parameter_receives_a_gradient() {
    let cfg = tiny();
    assert_gradients_reach_every_parameter(Colf::init(&cfg, 1).unwrap());
}

/// Slot latents and light fields of two test images (the second inverted), 3 foreground slots.
fn prepared_fields(colf: &Colf) -> (colf::model::SlotWeights, RayBatch) {
    let cfg = colf.config().clone();
    let model = colf.model();
    let dev = Device::Cpu;
    let s = cfg.encoder_size;
    let mut images = test_image(s);
    images.extend(test_image(s).iter().map(|v| 1.0 - v));
    // [2, S, S, 3] → [2, 3, S, S]
    let images = Tensor::from_vec(images, (2, s, s, 3), &dev)
        .unwrap()
        .permute((0, 3, 1, 2))
        .unwrap()
        .contiguous()
        .unwrap();
    let mut rng = StdRng::seed_from_u64(0);
    let k = 3;
    let slots = model.encode(&images, k, &mut rng).unwrap();
    let fields = model.prepare(&slots.fg, &slots.bg).unwrap();
    let frames = vec![DMat4::from_translation(DVec3::new(0.5, 0.0, 0.0)); k];
    let (o1, d1) = camera_rays(DVec3::new(6.0, 2.0, 4.0), 6);
    let (o2, d2) = camera_rays(DVec3::new(-3.0, 5.0, 4.0), 6);
    let rays = RayBatch::new(
        &cfg,
        &[
            SceneRays {
                slot_to_world: &frames,
                origins: &o1,
                dirs: &d1,
            },
            SceneRays {
                slot_to_world: &frames,
                origins: &o2,
                dirs: &d2,
            },
        ],
        &dev,
    )
    .unwrap();
    (fields, rays)
}

/// Colours and compositor weights of two views rendered by `colf`.
fn rendered(colf: &Colf) -> [Tensor; 2] {
    let (fields, rays) = prepared_fields(colf);
    let out = colf.model().decode(&fields, &rays).unwrap();
    [out.rgb, out.weights]
}

/// A loss on two rendered views of `colf`'s model sends a non-zero gradient to every
/// parameter; returns the gradients by parameter name.
fn assert_gradients_reach_every_parameter(colf: Colf) -> Vec<(String, Tensor)> {
    let colf = colf.into_trainable().unwrap();
    let dev = Device::Cpu;
    let (fields, rays) = prepared_fields(&colf);
    let out = colf.model().decode(&fields, &rays).unwrap();
    let target = Tensor::full(0.3f32, out.rgb.shape(), &dev).unwrap();
    let loss = (out.rgb - target)
        .unwrap()
        .sqr()
        .unwrap()
        .mean_all()
        .unwrap();
    let grads = loss.backward().unwrap();
    let vars = colf.named_vars();
    assert_eq!(vars.len(), colf.parameters().len());
    let mut missing = Vec::new();
    let mut all = Vec::new();
    for (name, var) in &vars {
        match grads.get(var.as_tensor()) {
            Some(g) if abs_sum(g) > 0.0 => all.push((name.clone(), g.clone())),
            _ => missing.push(name.clone()),
        }
    }
    assert!(missing.is_empty(), "no gradient reached: {missing:?}");
    all
}

/// How far `b` is from `reference`, relative to its size: Σ|reference − b| / Σ|reference|.
fn relative_gap(reference: &Tensor, b: &Tensor) -> f32 {
    abs_sum(&(reference - b).unwrap()) / abs_sum(reference)
}

/// The tiny config with a zero background latent (what `static_background` and an
/// image-dependent background grow from).
fn zero_background_tiny() -> Config {
    Config {
        zero_background: true,
        ..tiny()
    }
}

/// Values drawn from N(0, std²) in `shape`, seeded (candle's `randn` is not).
fn seeded_normal(std: f32, shape: &[usize], seed: u64) -> Tensor {
    use rand_distr::{Distribution, Normal};
    let normal = Normal::new(0f32, std).unwrap();
    let mut rng = StdRng::seed_from_u64(seed);
    let n = shape.iter().product();
    let values: Vec<f32> = (0..n).map(|_| normal.sample(&mut rng)).collect();
    Tensor::from_vec(values, shape, &Device::Cpu).unwrap()
}

fn abs_sum(t: &Tensor) -> f32 {
    t.abs()
        .unwrap()
        .sum_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

#[test]
fn a_grown_model_computes_the_same_fields_and_trains_its_new_weights() {
    let cfg = zero_background_tiny();
    let small = Colf::init(&cfg, 3).unwrap();
    let grown_cfg = cfg
        .with_overrides(&[
            "static_background=true".to_string(),
            format!("hypernet_hidden={}", 2 * cfg.hypernet_hidden),
        ])
        .unwrap();
    let grown = small.reconfigured(&grown_cfg, 4, "m").unwrap();
    let grown_id = grown.identity().unwrap();
    assert!(grown
        .parameters()
        .keys()
        .all(|k| !k.starts_with("hypernet_bg.")));
    assert!(grown
        .parameters()
        .contains_key("background_field.layers.0.weight"));
    let (before, _) = prepared_fields(&small);
    let (after, _) = prepared_fields(&grown);
    for (lb, la) in before.layers.iter().zip(&after.layers) {
        for (tb, ta) in [(&lb.weight, &la.weight), (&lb.bias, &la.bias)] {
            let gap = relative_gap(tb, ta);
            assert!(gap < 1e-5, "generated light fields changed: {gap}");
        }
    }
    // Wider light fields too, from a hypernetwork background or a static one: same renders.
    let wider_fields = |c: &Config| {
        c.with_overrides(&[format!("lfn_hidden={}", 2 * cfg.lfn_hidden)])
            .unwrap()
    };
    let reference = rendered(&small);
    for wide in [
        small.reconfigured(&wider_fields(&cfg), 5, "m").unwrap(),
        grown
            .reconfigured(&wider_fields(&grown_cfg), 5, "m")
            .unwrap(),
    ] {
        let out = rendered(&wide);
        for (a, b) in reference.iter().zip(&out) {
            let gap = relative_gap(a, b);
            assert!(gap < 1e-5, "renders changed: {gap}");
        }
        // (With a zero background latent, `hypernet_bg.fc1.weight` gets no gradient: static
        // models only.)
        if wide.config().static_background {
            assert_gradients_reach_every_parameter(wide);
        }
    }
    // The new hidden units' output weights start at zero and receive gradients.
    let grads = assert_gradients_reach_every_parameter(grown);
    let (_, head) = grads
        .iter()
        .find(|(n, _)| n == "hypernet_fg.layers.0.weight.weight")
        .unwrap();
    let new_columns = head
        .narrow(1, cfg.hypernet_hidden, cfg.hypernet_hidden)
        .unwrap();
    assert!(abs_sum(&new_columns) > 0.0);
    // Growing is seeded, and shrinking or undoing is refused by name.
    let again = small.reconfigured(&grown_cfg, 4, "m").unwrap();
    assert_eq!(again.identity().unwrap(), grown_id);
    let narrower = grown_cfg
        .with_overrides(&[format!("hypernet_hidden={}", cfg.hypernet_hidden)])
        .unwrap();
    let err = again
        .reconfigured(&narrower, 4, "m.safetensors")
        .err()
        .unwrap();
    assert!(err.to_string().starts_with("m.safetensors: "), "{err}");
    // A background that reads the image is replaced, as the paper does for City-Block, by a
    // fresh static field (to be pretrained): the foreground is kept, and training reaches the
    // new field. The reader must go with it (a config keeping it is refused).
    let reading_cfg = Config {
        background_reader: true,
        ..tiny()
    };
    let reading = Colf::init(&reading_cfg, 3).unwrap();
    let city = ["zero_background=true", "static_background=true"].map(String::from);
    assert!(reading_cfg.with_overrides(&city).is_err());
    let mut without_reader = city.to_vec();
    without_reader.push("background_reader=false".into());
    let replaced = reading
        .reconfigured(
            &reading_cfg.with_overrides(&without_reader).unwrap(),
            4,
            "n",
        )
        .unwrap();
    let params = replaced.parameters();
    assert!(params
        .keys()
        .all(|k| !k.starts_with("hypernet_bg.") && !k.starts_with("background_reader.")));
    assert!(params.contains_key("background_field.layers.0.weight"));
    for (name, before) in reading.parameters() {
        if name.starts_with("hypernet_fg.") || name.starts_with("encoder.") {
            assert_eq!(relative_gap(before, &params[name]), 0.0, "{name}");
        }
    }
    assert_gradients_reach_every_parameter(replaced);
}

/// Floor features (`floor_fourier_freqs`) grown on a trained model: the light fields' new input
/// columns are read with zero weights, so the generated fields and the renders are the same;
/// training reaches those weights (the background's, through its hypernetwork or its static
/// field; the slots' floor columns are zeros, so their rows get none); more octaves grow the
/// same way; fewer, or with other Fourier features, are refused.
#[test]
fn floor_features_grow_with_the_same_renders_and_train() {
    for cfg in [
        tiny(),
        Config {
            static_background: true,
            ..zero_background_tiny()
        },
    ] {
        let plain = Colf::init(&cfg, 3).unwrap();
        let floor_cfg = cfg
            .with_overrides(&["floor_fourier_freqs=3".to_string()])
            .unwrap();
        let floor = plain.reconfigured(&floor_cfg, 4, "m").unwrap();
        let more_cfg = floor_cfg
            .with_overrides(&["floor_fourier_freqs=5".to_string()])
            .unwrap();
        let more = floor.reconfigured(&more_cfg, 5, "m").unwrap();
        let (before, rays) = prepared_fields(&plain);
        // The rays meet the floor: the background's floor columns are not all zero.
        let (in_old, in_new) = (cfg.ray_input_dim(), more_cfg.ray_input_dim());
        assert_eq!(in_new, in_old + 3 + 4 * 5);
        let reference = rendered(&plain);
        for grown in [&floor, &more] {
            let (after, grown_rays) = prepared_fields(grown);
            let in_dim = grown.config().ray_input_dim();
            let coords = grown_rays.coords.flatten_all().unwrap();
            let coords = coords.to_vec1::<f32>().unwrap();
            let hits = coords
                .chunks_exact(in_dim)
                .take(grown_rays.rays)
                .filter(|row| row[in_old] == 1.0)
                .count();
            assert_eq!(hits, grown_rays.rays, "every ray meets the floor");
            assert_eq!(rays.rays, grown_rays.rays);
            // The old inputs' weights are kept; the new inputs' are zero.
            for (lb, la) in before.layers.iter().zip(&after.layers).take(1) {
                let old_rows = la.weight.narrow(1, 0, in_old).unwrap();
                assert!(relative_gap(&lb.weight, &old_rows) < 1e-5);
                let new_rows = la.weight.narrow(1, in_old, in_dim - in_old).unwrap();
                assert_eq!(abs_sum(&new_rows), 0.0);
            }
            for (lb, la) in before.layers.iter().zip(&after.layers).skip(1) {
                for (tb, ta) in [(&lb.weight, &la.weight), (&lb.bias, &la.bias)] {
                    assert!(
                        relative_gap(tb, ta) < 1e-5,
                        "generated light fields changed"
                    );
                }
            }
            for (a, b) in reference.iter().zip(&rendered(grown)) {
                let gap = relative_gap(a, b);
                assert!(gap < 1e-6, "renders changed: {gap}");
            }
        }
        let grads = assert_gradients_reach_every_parameter(more);
        let grad = |name: &str| grads.iter().find(|(n, _)| n == name).unwrap().1.clone();
        // A layer-0 weight (generated or static) laid out as [in, out, …]: the new inputs' part.
        let new_rows = |g: &Tensor| {
            let per_input = g.elem_count() / in_new;
            g.reshape((in_new, per_input))
                .unwrap()
                .narrow(0, in_old, in_new - in_old)
                .unwrap()
        };
        let background = if cfg.static_background {
            new_rows(&grad("background_field.layers.0.weight"))
        } else {
            new_rows(&grad("hypernet_bg.layers.0.weight.weight"))
        };
        assert!(
            abs_sum(&background) > 0.0,
            "the floor weights get no gradient"
        );
        let slots = new_rows(&grad("hypernet_fg.layers.0.weight.weight"));
        assert_eq!(
            abs_sum(&slots),
            0.0,
            "the slots' floor columns are not zeros"
        );
        // Fewer octaves, or floor features with other Fourier features, are refused.
        let err = refused_growth(&more_cfg, "floor_fourier_freqs=3");
        assert!(err.contains("floor_fourier_freqs"), "{err}");
        let err = refused_growth(&more_cfg, "floor_fourier_freqs=0");
        assert!(err.contains("floor_fourier_freqs"), "{err}");
        let both = format!("ray_fourier_freqs={}", cfg.ray_fourier_freqs + 1);
        let to = more_cfg.with_overrides(&[both]).unwrap();
        assert!(floor.reconfigured(&to, 4, "m").is_err());
        // Configuring (the same tensors' shapes) cannot add them.
        assert!(plain
            .configured(&["floor_fourier_freqs=3".to_string()])
            .is_err());
    }
}

/// A model file written before `floor_fourier_freqs` existed reads with the setting off, and
/// its config serialises without the key, so its identity recomputed from the re-serialised
/// config is the one it carries.
#[test]
fn a_bundled_model_keeps_its_identity_without_floor_features() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/supervised.safetensors");
    let model = Colf::load(&path).unwrap();
    assert_eq!(model.config().floor_fourier_freqs, 0);
    assert!(!model.config().to_json().contains("floor_fourier_freqs"));
    let carried = model.identity().unwrap();
    assert_eq!(model.into_trainable().unwrap().identity().unwrap(), carried);
}

/// Per-layer hypernetwork hidden layers (`hypernet_per_layer`): grown from a shared one they
/// render the same, each layer then has hidden units of its own that train, they widen like a
/// shared one, and they cannot be merged back.
#[test]
fn per_layer_hypernetwork_hidden_layers_grow_from_a_shared_one() {
    let cfg = tiny();
    let shared = Colf::init(&cfg, 3).unwrap();
    let per_layer_cfg = cfg
        .with_overrides(&["hypernet_per_layer=true".to_string()])
        .unwrap();
    let split = shared.reconfigured(&per_layer_cfg, 4, "m").unwrap();
    let layers = cfg.lfn_dims().len() - 1;
    for prefix in ["hypernet_fg.", "hypernet_bg."] {
        assert!(!split
            .parameters()
            .contains_key(&format!("{prefix}fc1.weight")));
        for l in 0..layers {
            let name = format!("{prefix}layers.{l}.fc1.weight");
            let copy = &split.parameters()[&name];
            let original = &shared.parameters()[&format!("{prefix}fc1.weight")];
            assert_eq!(relative_gap(original, copy), 0.0, "{name}");
        }
    }
    let reference = rendered(&shared);
    let widened_cfg = per_layer_cfg
        .with_overrides(&[format!("hypernet_hidden={}", 2 * cfg.hypernet_hidden)])
        .unwrap();
    let widened = split.reconfigured(&widened_cfg, 5, "m").unwrap();
    for model in [&split, &widened] {
        for (a, b) in reference.iter().zip(&rendered(model)) {
            let gap = relative_gap(a, b);
            assert!(gap < 1e-6, "renders changed: {gap}");
        }
    }
    assert_eq!(
        widened.parameters()["hypernet_fg.layers.1.fc1.weight"].dims(),
        &[2 * cfg.hypernet_hidden, cfg.slot_dim]
    );
    assert_eq!(
        widened.parameters()["hypernet_fg.layers.1.weight.weight"]
            .dim(1)
            .unwrap(),
        2 * cfg.hypernet_hidden
    );
    // Every layer's own hidden layer is trained (and a fresh per-layer model's too).
    let grads = assert_gradients_reach_every_parameter(split);
    assert!(grads
        .iter()
        .any(|(n, _)| n == "hypernet_fg.layers.2.fc1.bias"));
    assert_gradients_reach_every_parameter(Colf::init(&per_layer_cfg, 6).unwrap());
    let err = widened.reconfigured(&cfg, 4, "w").err().unwrap();
    assert!(err.to_string().starts_with("w: "), "{err}");
}

#[test]
fn a_model_grown_to_the_paper_decoders_shape_renders_the_same_and_trains_it_all() {
    // The bundled small decoder grown to the `paper` preset's shape (wider light fields and
    // features, wider and deeper heads and compositor), here on the tiny model with shadows.
    let cfg = Config {
        shadow_head: true,
        ..tiny()
    };
    let small = Colf::init(&cfg, 3).unwrap();
    let paper_shape = [
        format!("lfn_hidden={}", 2 * cfg.lfn_hidden),
        format!("lfn_features={}", 2 * cfg.lfn_features),
        format!("head_hidden={}", 2 * cfg.head_hidden),
        "head_hidden_layers=3".into(),
        format!("compositor_hidden={}", 4 * cfg.compositor_hidden),
        "compositor_hidden_layers=3".into(),
    ];
    let grown_cfg = cfg.with_overrides(&paper_shape).unwrap();
    let grown = small.reconfigured(&grown_cfg, 4, "m").unwrap();
    let params = grown.parameters();
    assert_eq!(params["heads.color.layers.3.weight"].dims(), [3, 16]);
    assert_eq!(params["compositor.v.layers.3.weight"].dims(), [1, 32]);
    assert_eq!(params["heads.shadow.weight"].dims(), [1, 16]);
    // Shadows visible, so the growth of the shadow head's input is checked too.
    let shadowed = |c: Colf| {
        c.with_tensor(
            "heads.shadow.bias",
            Tensor::new(&[0.05f32], &Device::Cpu).unwrap(),
        )
        .unwrap()
    };
    let (small, grown) = (shadowed(small), shadowed(grown));
    for (a, b) in rendered(&small).iter().zip(&rendered(&grown)) {
        let gap = relative_gap(a, b);
        assert!(gap < 1e-5, "renders changed: {gap}");
    }
    // Every new weight trains, the zero weights that read the new units and features included.
    let grads = assert_gradients_reach_every_parameter(grown);
    let grad = |name: &str| grads.iter().find(|(n, _)| n == name).unwrap().1.clone();
    let reads_new_units = grad("heads.ordering.layers.3.weight")
        .narrow(1, cfg.head_hidden, cfg.head_hidden)
        .unwrap();
    assert!(abs_sum(&reads_new_units) > 0.0);
    let reads_new_features = grad("heads.color.layers.0.weight")
        .narrow(1, cfg.lfn_features, cfg.lfn_features)
        .unwrap();
    assert!(abs_sum(&reads_new_features) > 0.0);
    // Shrinking is refused, naming the file.
    let err = refused_growth(&grown_cfg, "head_hidden_layers=2");
    assert!(err.starts_with("m.safetensors: "), "{err}");
}

/// Slot attention's output for the test image with the initial noise `noise` [1, 1 + K, D].
fn slots(colf: &Colf, noise: &Tensor) -> colf::model::SlotOutput {
    let s = colf.config().encoder_size;
    let images = Tensor::from_vec(test_image(s), (1, s, s, 3), &Device::Cpu)
        .unwrap()
        .permute((0, 3, 1, 2))
        .unwrap()
        .contiguous()
        .unwrap();
    let model = colf.model();
    let tokens = model.encoder.forward(&images).unwrap();
    model
        .slot_attention
        .forward_with_noise(&tokens, noise)
        .unwrap()
}

/// The error of growing a fresh `cfg` model (file name `m.safetensors`) with `setting`.
fn refused_growth(cfg: &Config, setting: &str) -> String {
    let to = cfg.with_overrides(&[setting.to_string()]).unwrap();
    let Err(err) = Colf::init(cfg, 1)
        .unwrap()
        .reconfigured(&to, 4, "m.safetensors")
    else {
        panic!("`{setting}` was accepted");
    };
    err.to_string()
}

#[test]
fn wider_slots_keep_each_value_in_copies_and_compute_the_same() {
    // slot_dim 8 → 16 (the `paper` preset's 128 from the bundled 64), with a shared hypernetwork
    // hidden layer and with one per light-field layer.
    for per_layer in [false, true] {
        let cfg = Config {
            hypernet_per_layer: per_layer,
            ..tiny()
        };
        let (d, m) = (cfg.slot_dim, 2);
        let small = Colf::init(&cfg, 3).unwrap();
        let wide_cfg = cfg
            .with_overrides(&[format!("slot_dim={}", m * d)])
            .unwrap();
        let wide = small.reconfigured(&wide_cfg, 4, "m").unwrap();
        // The same image and the same initial noise in every copy: the same attention, slots
        // held m times, the same light fields.
        let noise = seeded_normal(1.0, &[1, 4, d], 9);
        let copied = Tensor::cat(&[&noise, &noise], 2).unwrap();
        let (before, after) = (slots(&small, &noise), slots(&wide, &copied));
        let gap = relative_gap(&before.log_attention, &after.log_attention);
        assert!(gap < 1e-5, "attention changed: {gap}");
        for (old, new) in [(&before.fg, &after.fg), (&before.bg, &after.bg)] {
            let last = old.rank() - 1;
            let held_twice = Tensor::cat(&[old, old], last).unwrap();
            let gap = relative_gap(&held_twice, new);
            assert!(gap < 1e-5, "slots changed: {gap}");
        }
        let fields = |colf: &Colf, out: &colf::model::SlotOutput| {
            colf.model().prepare(&out.fg, &out.bg).unwrap()
        };
        let (old_fields, new_fields) = (fields(&small, &before), fields(&wide, &after));
        for (lb, la) in old_fields.layers.iter().zip(&new_fields.layers) {
            for (tb, ta) in [(&lb.weight, &la.weight), (&lb.bias, &la.bias)] {
                let gap = relative_gap(tb, ta);
                assert!(gap < 1e-5, "light fields changed: {gap}");
            }
        }
        // The hypernetworks read the copies with different weights that sum to the old ones,
        // so the copies can move apart.
        let fc1 = if per_layer {
            "hypernet_fg.layers.0.fc1.weight"
        } else {
            "hypernet_fg.fc1.weight"
        };
        let (old_fc1, new_fc1) = (&small.parameters()[fc1], &wide.parameters()[fc1]);
        let (first, second) = (
            new_fc1.narrow(1, 0, d).unwrap(),
            new_fc1.narrow(1, d, d).unwrap(),
        );
        assert!(relative_gap(&first, &second) > 0.05);
        let gap = relative_gap(old_fc1, &(first + second).unwrap());
        assert!(gap < 1e-5, "{gap}");
        assert_gradients_reach_every_parameter(wide);
    }
    // Only whole multiples keep the slots' values.
    let cfg = tiny();
    let err = refused_growth(&cfg, &format!("slot_dim={}", cfg.slot_dim + 3));
    assert!(
        err.contains("whole multiple") && err.contains("fresh"),
        "{err}"
    );
}

#[test]
fn wider_slots_with_fresh_values_draw_the_same_fields_and_read_the_new_values() {
    // slot_dim 8 → 20 (not a multiple: fresh values grow to any width), with and without the
    // hypernetworks' RMS norm, a shared hidden layer and one per light-field layer, and a
    // background reader (whose new latent values start at zero too).
    let fresh = |seed| Growth {
        seed,
        slot_values: SlotValues::Fresh,
    };
    for (per_layer, rms_norm, reader) in [
        (false, true, false),
        (true, true, true),
        (true, false, false),
    ] {
        let cfg = Config {
            hypernet_per_layer: per_layer,
            hypernet_rms_norm: rms_norm,
            background_reader: reader,
            ..tiny()
        };
        let (d, wide_d) = (cfg.slot_dim, 20);
        let small = Colf::init(&cfg, 3).unwrap();
        let wide_cfg = cfg.with_overrides(&[format!("slot_dim={wide_d}")]).unwrap();
        let wide = small.grown(&wide_cfg, fresh(4), "m").unwrap();
        // Given latents, the new values zero: the same light fields.
        let fg = seeded_normal(1.0, &[1, 3, d], 5);
        let bg = seeded_normal(1.0, &[1, d], 6);
        let padded = |t: &Tensor| {
            let mut shape = t.dims().to_vec();
            *shape.last_mut().unwrap() = wide_d - d;
            let zeros = Tensor::zeros(shape, DType::F32, &Device::Cpu).unwrap();
            Tensor::cat(&[t, &zeros], t.rank() - 1).unwrap()
        };
        let before = small.model().prepare(&fg, &bg).unwrap();
        let after = wide.model().prepare(&padded(&fg), &padded(&bg)).unwrap();
        for (lb, la) in before.layers.iter().zip(&after.layers) {
            for (tb, ta) in [(&lb.weight, &la.weight), (&lb.bias, &la.bias)] {
                let gap = relative_gap(tb, ta);
                assert!(gap < 1e-4, "light fields changed: {gap}");
            }
        }
        // The new values are read at once: a latent with only new values draws other fields.
        let only_new = Tensor::cat(
            &[
                &Tensor::zeros((1, 3, d), DType::F32, &Device::Cpu).unwrap(),
                &seeded_normal(1.0, &[1, 3, wide_d - d], 7),
            ],
            2,
        )
        .unwrap();
        let moved = wide.model().prepare(&only_new, &padded(&bg)).unwrap();
        let zero_fg = wide
            .model()
            .prepare(&padded(&(&fg * 0.0).unwrap()), &padded(&bg))
            .unwrap();
        assert!(relative_gap(&zero_fg.layers[0].weight, &moved.layers[0].weight) > 1e-2);
        // Slot attention: the same image and noise give new values near zero, and attention
        // near the old (not the same: the layer norms see the zeros, which is exact only for
        // zero-mean slots, and this untrained model's have a mean of about 1.8).
        let noise = seeded_normal(1.0, &[1, 4, d], 9);
        let wide_noise =
            Tensor::cat(&[&noise, &seeded_normal(1.0, &[1, 4, wide_d - d], 8)], 2).unwrap();
        let (before, after) = (slots(&small, &noise), slots(&wide, &wide_noise));
        let gap = relative_gap(&before.log_attention, &after.log_attention);
        assert!(gap < 0.25, "attention changed: {gap}");
        let new_values = after.fg.narrow(2, d, wide_d - d).unwrap();
        let share = abs_sum(&new_values) / abs_sum(&after.fg);
        assert!(share < 1e-3, "new values start at {share} of the slots");
        // The queries: the old block scaled by √(new/old) for the attention's 1/√D (the keys'
        // new rows meet zero query rows), nothing else.
        let key = "slot_attention.fg.to_q.weight";
        let (old_q, new_q) = (&small.parameters()[key], &wide.parameters()[key]);
        let kept = new_q.narrow(0, 0, d).unwrap().narrow(1, 0, d).unwrap();
        let scaled = (old_q * (wide_d as f64 / d as f64).sqrt()).unwrap();
        assert!(relative_gap(&scaled, &kept) < 1e-6);
        assert_eq!(abs_sum(new_q) - abs_sum(&kept), 0.0);
        assert_gradients_reach_every_parameter(wide);
    }
    // A narrower slot is refused either way.
    let cfg = tiny();
    let narrower = cfg.with_overrides(&["slot_dim=4".to_string()]).unwrap();
    let Err(err) = Colf::init(&cfg, 1)
        .unwrap()
        .grown(&narrower, fresh(4), "m.safetensors")
    else {
        panic!("a narrower slot was accepted");
    };
    assert!(err.to_string().contains("not shrink"), "{err}");
}

#[test]
fn a_fixed_background_grows_into_one_that_reads_the_image() {
    let cfg = zero_background_tiny();
    let fixed = Colf::init(&cfg, 3).unwrap();
    let following_cfg = cfg
        .with_overrides(&["zero_background=false".into()])
        .unwrap();
    let following = fixed.reconfigured(&following_cfg, 4, "m").unwrap();
    assert!(!following.config().zero_background);
    let gap = |a: &[Tensor; 2], b: &[Tensor; 2]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| relative_gap(x, y))
            .fold(0.0f32, f32::max)
    };
    // The background latent now comes from slot attention, yet the renders are unchanged...
    let reference = rendered(&fixed);
    assert!(gap(&reference, &rendered(&following)) < 1e-6);
    // ...because the input weights that read it start at zero: with the old ones (never
    // trained), the same latent changes the background.
    let unzeroed = fixed.configured(&["zero_background=false".into()]).unwrap();
    assert!(gap(&reference, &rendered(&unzeroed)) > 1e-3);
    // Training reaches every parameter, the zeroed weights included.
    let grads = assert_gradients_reach_every_parameter(following);
    assert!(grads.iter().any(|(n, _)| n == "hypernet_bg.fc1.weight"));
}

#[test]
fn a_background_reader_grows_on_a_fixed_background_and_follows_the_image() {
    let cfg = zero_background_tiny();
    let fixed = Colf::init(&cfg, 3).unwrap();
    let reader_cfg = cfg
        .with_overrides(&[
            "zero_background=false".into(),
            "background_reader=true".into(),
        ])
        .unwrap();
    let reading = fixed.reconfigured(&reader_cfg, 4, "m").unwrap();
    assert!(reading.config().background_reader);
    // Grown, it renders as the fixed background did (the reader's latent meets zeroed input
    // weights)...
    let [rgb_fixed, weights_fixed] = rendered(&fixed);
    let [rgb_reading, weights_reading] = rendered(&reading);
    assert!(relative_gap(&rgb_fixed, &rgb_reading) < 1e-6);
    assert!(relative_gap(&weights_fixed, &weights_reading) < 1e-6);
    // ...but its background latent is read from the image: a darker image gives another one.
    let side = cfg.encoder_size;
    let image = test_image(side);
    let darker: Vec<f32> = image.iter().map(|v| v * 0.5).collect();
    let a = reading.encode(&image, side, side, 3, 1).unwrap();
    let b = reading.encode(&darker, side, side, 3, 1).unwrap();
    let moved = a
        .bg_latent
        .iter()
        .zip(&b.bg_latent)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(moved > 1e-3, "{moved}");
    // The reader's gradient passes through the zeroed input weights, so it flows once the first
    // step has moved them (the first step's gradient of those weights is the hidden layer's
    // times the reader's latent); then training reaches every parameter.
    let fc1 = reading.parameters()["hypernet_bg.fc1.weight"].clone();
    let stepped = reading
        .with_tensor(
            "hypernet_bg.fc1.weight",
            seeded_normal(1e-3, fc1.dims(), 11),
        )
        .unwrap();
    let grads = assert_gradients_reach_every_parameter(stepped);
    for name in ["background_reader.proj.weight", "hypernet_bg.fc1.weight"] {
        assert!(grads.iter().any(|(n, _)| n == name), "{name}");
    }
    // It grows only where the renders start unchanged, and is never removed.
    let following = fixed
        .reconfigured(
            &cfg.with_overrides(&["zero_background=false".into()])
                .unwrap(),
            4,
            "f",
        )
        .unwrap();
    let err = following
        .reconfigured(&reader_cfg, 4, "f.safetensors")
        .err()
        .unwrap();
    assert!(err.to_string().contains("zero background"), "{err}");
    let back = reader_cfg
        .with_overrides(&["background_reader=false".into()])
        .unwrap();
    let err = reading
        .reconfigured(&back, 4, "g.safetensors")
        .err()
        .unwrap();
    assert!(err.to_string().contains("cannot be removed"), "{err}");
    // And it needs an image-dependent background.
    let err = cfg
        .with_overrides(&["background_reader=true".into()])
        .err()
        .unwrap();
    assert!(err.to_string().contains("zero_background"), "{err}");
}

#[test]
fn a_shadow_head_starts_faint_and_darkens_only_the_background() {
    shadow_head_checks(&[]);
    shadow_head_checks(&["shadow_light=[30, 55]".into()]);
}

/// The shadow head's properties with shadows read from the rays, or (`shadow_light`) from
/// their shadow lines.
fn shadow_head_checks(light: &[String]) {
    let cfg = tiny();
    let plain = Colf::init(&cfg, 3).unwrap();
    let mut overrides = vec!["shadow_head=true".to_string()];
    overrides.extend_from_slice(light);
    let shadow_cfg = cfg.with_overrides(&overrides).unwrap();
    let faint = plain.reconfigured(&shadow_cfg, 4, "m").unwrap();
    // Grown: the same segmentation, colours darker by at most 3 × softplus(−8) ≈ 0.1 %.
    let [rgb_plain, weights_plain] = rendered(&plain);
    let [rgb_faint, weights_faint] = rendered(&faint);
    assert_eq!(abs_sum(&(&weights_plain - &weights_faint).unwrap()), 0.0);
    let gap = relative_gap(&rgb_plain, &rgb_faint);
    assert!(gap > 0.0 && gap < 1.1e-3, "{gap}");
    // Every parameter trains from the start, the shadow head's zero weights included.
    let grads =
        assert_gradients_reach_every_parameter(plain.reconfigured(&shadow_cfg, 4, "m").unwrap());
    assert!(grads.iter().any(|(n, _)| n == "heads.shadow.weight"));
    // Stronger shadows: the segmentation is unchanged and colours only get darker (the
    // background's colour is multiplied by exp(−Σσ) ≤ 1).
    let strong = faint
        .with_tensor(
            "heads.shadow.bias",
            Tensor::new(&[-0.1f32], &Device::Cpu).unwrap(),
        )
        .unwrap();
    let [rgb_strong, weights_strong] = rendered(&strong);
    assert_eq!(abs_sum(&(&weights_plain - &weights_strong).unwrap()), 0.0);
    let brighter = (&rgb_strong - &rgb_plain).unwrap().relu().unwrap();
    assert!(abs_sum(&brighter) < 1e-6, "a shadow brightened a pixel");
    assert!(relative_gap(&rgb_plain, &rgb_strong) > 0.05);
    // The shadow goes with its slot: with no foreground slots there is none.
    let (o, d) = camera_rays(DVec3::new(6.0, 2.0, 4.0), 5);
    let bg = vec![0.2f32; cfg.slot_dim];
    let alone = |m: &Colf| {
        let prepared = m.prepare(&[], &bg).unwrap();
        m.render_rays(&prepared, &[], &o, &d).unwrap()
    };
    let (a, b) = (alone(&plain), alone(&strong));
    assert_eq!(a.rgb, b.rgb);
    assert!(b.shadow.iter().all(|&v| v == 0.0));
    // A shadow head is not removed by reconfiguring; with_tensor checks shapes.
    let err = strong.reconfigured(&cfg, 4, "m.safetensors").err().unwrap();
    assert!(err.to_string().contains("shadow head"), "{err}");
    assert!(strong
        .with_tensor(
            "heads.shadow.bias",
            Tensor::zeros(2, DType::F32, &Device::Cpu).unwrap()
        )
        .is_err());
}

#[test]
fn encode_is_seeded_and_handles_any_slot_count() {
    let colf = Colf::init(&Config::small(), 0).unwrap();
    let img = test_image(40);
    let a = colf.encode(&img, 40, 40, 7, 11).unwrap();
    let b = colf.encode(&img, 40, 40, 7, 11).unwrap();
    let c = colf.encode(&img, 40, 40, 7, 12).unwrap();
    assert_eq!(a, b);
    assert_ne!(a.fg_latents, c.fg_latents);
    assert_eq!(a.fg_latents.len(), 7);
    assert!(a.slot_mass.iter().all(|m| (0.0..=1.0).contains(m)));
    assert!(a.slot_mass.iter().sum::<f32>() <= 1.0 + 1e-4);
    for k in [0, 1, 30] {
        let e = colf.encode(&img, 40, 40, k, 0).unwrap();
        assert_eq!(e.fg_latents.len(), k);
        assert_eq!(e.slot_mass.len(), k);
        assert!(all_finite(&e.bg_latent));
    }
    // Images of other sizes and out-of-range values are resized and clamped.
    let big: Vec<f32> = (0..300 * 200 * 3).map(|i| (i % 11) as f32 - 3.0).collect();
    assert!(colf.encode(&big, 200, 300, 3, 0).is_ok());
    assert!(colf.encode(&big, 10, 10, 3, 0).is_err());
}

/// Renders `k` copies of a slot with the given frames from a camera; checks finiteness and
/// that weights sum to 1.
fn render_check(colf: &Colf, frames: &[DMat4], eye: DVec3, n: usize) -> colf::model::RayOutput {
    let img = test_image(32);
    let enc = colf.encode(&img, 32, 32, 1, 0).unwrap();
    let fg = vec![enc.fg_latents[0].clone(); frames.len()];
    let prepared = colf.prepare(&fg, &enc.bg_latent).unwrap();
    let (o, d) = camera_rays(eye, n);
    let out = colf.render_rays(&prepared, frames, &o, &d).unwrap();
    assert_eq!(out.fields, frames.len() + 1);
    assert_eq!(out.rgb.len(), 3 * n * n);
    assert!(all_finite(&out.rgb) && all_finite(&out.weights) && all_finite(&out.ordering));
    assert!(out.rgb.iter().all(|v| (0.0..=1.0).contains(v)));
    for row in out.weights.chunks_exact(out.fields) {
        let sum: f32 = row.iter().sum();
        assert!((sum - 1.0).abs() < 1e-4, "weights sum to {sum}");
    }
    out
}

#[test]
fn renders_stay_finite_at_extremes() {
    // The default config, and slot frames at attention centroids with a locality bound (whose
    // ρ²/r grows to ~10⁸ for slots 10⁴ units away).
    let mut local = Config::small();
    local.attention_frames = true;
    local.fg_locality = 2.0;
    for cfg in [Config::small(), local] {
        extremes_stay_finite(&cfg);
    }
}

fn extremes_stay_finite(cfg: &Config) {
    let colf = Colf::init(cfg, 0).unwrap();
    let eye = DVec3::new(8.0, -9.0, 8.0);
    render_check(&colf, &[], eye, 8); // background only
    render_check(&colf, &[DMat4::IDENTITY], eye, 8);
    let many: Vec<DMat4> = (0..200)
        .map(|i| DMat4::from_translation(DVec3::new((i % 20) as f64 * 0.3, (i / 20) as f64, 0.0)))
        .collect();
    render_check(&colf, &many, eye, 6);
    // Slots moved 10⁴ units away, rotated.
    let far = [
        DMat4::from_translation(DVec3::new(1e4, 0.0, 0.0)),
        DMat4::from_rotation_translation(
            glam::DQuat::from_rotation_z(1.0),
            DVec3::new(-1e4, 3e4, 1e4),
        ),
        DMat4::IDENTITY,
    ];
    render_check(&colf, &far, eye, 6);
    // A camera 10⁴ units away, looking at the origin.
    render_check(&colf, &far, DVec3::new(1e4, 5e3, 2e3), 6);
    // Rays (nearly) parallel to each axis.
    for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
        let o = vec![DVec3::new(1.0, 2.0, 3.0) - 20.0 * axis; 3];
        let d = vec![axis, axis + DVec3::splat(1e-9), -axis + DVec3::splat(1e-12)];
        let enc = colf.encode(&test_image(16), 16, 16, 2, 0).unwrap();
        let prepared = colf.prepare(&enc.fg_latents, &enc.bg_latent).unwrap();
        let out = colf
            .render_rays(&prepared, &[DMat4::IDENTITY, far[1]], &o, &d)
            .unwrap();
        assert!(all_finite(&out.rgb) && all_finite(&out.weights));
    }
}

#[test]
fn bad_rays_and_frames_are_errors_not_nans() {
    let colf = Colf::init(&Config::small(), 0).unwrap();
    let enc = colf.encode(&test_image(16), 16, 16, 1, 0).unwrap();
    let prepared = colf.prepare(&enc.fg_latents, &enc.bg_latent).unwrap();
    let o = [DVec3::ZERO];
    assert!(colf
        .render_rays(&prepared, &[DMat4::IDENTITY], &o, &[DVec3::ZERO])
        .is_err());
    assert!(colf
        .render_rays(&prepared, &[DMat4::ZERO], &o, &[DVec3::X])
        .is_err());
    assert!(colf.render_rays(&prepared, &[], &o, &[DVec3::X]).is_err());
    let empty = colf
        .render_rays(&prepared, &[DMat4::IDENTITY], &[], &[])
        .unwrap();
    assert!(empty.rgb.is_empty());
    assert!(colf.prepare(&[vec![0.0; 3]], &enc.bg_latent).is_err());
}

#[test]
fn moved_copies_composite_front_to_back() {
    let colf = Colf::init(&Config::small(), 0).unwrap();
    let enc = colf.encode(&test_image(32), 32, 32, 1, 0).unwrap();
    let slot = enc.fg_latents[0].clone();
    let prepared = colf.prepare(&[slot.clone(), slot], &enc.bg_latent).unwrap();
    // A ray along −Z from z = 40 (and a tilted one); the two copies sit on the ray at
    // depths 10 and 10 + gap; which copy is listed first must not matter.
    let dir = DVec3::new(0.1, -0.05, -1.0).normalize();
    let origin = DVec3::new(0.3, 0.2, 40.0);
    for gap in [8.0, 30.0, 1e4] {
        let near = DMat4::from_translation(origin + 10.0 * dir);
        let far = DMat4::from_translation(origin + (10.0 + gap) * dir);
        for (frames, near_col) in [([near, far], 1), ([far, near], 2)] {
            let out = colf
                .render_rays(&prepared, &frames, &[origin], &[dir])
                .unwrap();
            let far_col = 3 - near_col;
            let (wn, wf) = (out.weights[near_col], out.weights[far_col]);
            assert!(wn > wf, "gap {gap}: near weight {wn} ≤ far weight {wf}");
            let (on, of) = (out.ordering[near_col], out.ordering[far_col]);
            assert!(
                ((of - on) as f64 - gap).abs() < 1e-3 * gap,
                "ordering values {on}, {of}"
            );
        }
    }
}

#[test]
fn chunked_rendering_matches_one_batch() {
    let colf = Colf::init(&Config::small(), 0).unwrap();
    let enc = colf.encode(&test_image(32), 32, 32, 3, 0).unwrap();
    let prepared = colf.prepare(&enc.fg_latents, &enc.bg_latent).unwrap();
    let frames = [DMat4::IDENTITY; 3];
    let chunk = colf.rays_per_chunk(4);
    let n = ((chunk + 100) as f64).sqrt().ceil() as usize;
    let (o, d) = camera_rays(DVec3::new(5.0, 6.0, 7.0), n);
    let all = colf.render_rays(&prepared, &frames, &o, &d).unwrap();
    let tail = colf
        .render_rays(&prepared, &frames, &o[chunk..], &d[chunk..])
        .unwrap();
    let k = 3 * chunk;
    for (a, b) in all.rgb[k..].iter().zip(&tail.rgb) {
        assert!((a - b).abs() < 1e-5);
    }
}

#[test]
fn checkpoints_round_trip_and_are_reproducible() {
    let cfg = tiny();
    let a = Colf::init(&cfg, 5).unwrap();
    let (bytes, id) = a.to_bytes().unwrap();
    assert_eq!(bytes, Colf::init(&cfg, 5).unwrap().to_bytes().unwrap().0);
    assert_ne!(id, Colf::init(&cfg, 6).unwrap().identity().unwrap());
    assert_eq!(id, a.identity().unwrap());
    assert_eq!(id.len(), 16);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.safetensors");
    assert_eq!(a.save(&path).unwrap(), id);
    let b = Colf::load(&path).unwrap();
    assert_eq!(b.identity().unwrap(), id);
    assert_eq!(b.config(), &cfg);
    assert_eq!(b.to_bytes().unwrap().0, bytes);
    let img = test_image(20);
    assert_eq!(
        a.encode(&img, 20, 20, 2, 3).unwrap(),
        b.encode(&img, 20, 20, 2, 3).unwrap()
    );
    // Training changes the identity.
    let t = b.into_trainable().unwrap();
    let (name, var) = &t.named_vars()[0];
    var.set(&(var.as_tensor() + 1.0).unwrap()).unwrap();
    assert_ne!(t.identity().unwrap(), id, "{name}");
    assert_ne!(t.to_bytes().unwrap().0, bytes);
}

#[test]
fn reconfigured_keeps_weights_and_refuses_shape_changes() {
    let cfg = tiny();
    let a = Colf::init(&cfg, 5).unwrap();
    let more_slots = cfg
        .with_overrides(&["default_slots=9".to_string()])
        .unwrap();
    let b = a.reconfigured(&more_slots, 0, "m").unwrap();
    assert_eq!(b.config().default_slots, 9);
    for ((name_a, ta), (name_b, tb)) in a.parameters().iter().zip(b.parameters()) {
        assert_eq!(name_a, name_b);
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(flat(ta), flat(tb), "{name_a}");
    }
    assert_ne!(
        b.identity().unwrap(),
        a.identity().unwrap(),
        "the config is part of the identity"
    );
    let (bytes, id) = b.to_bytes().unwrap();
    assert_eq!(
        Colf::from_bytes(&bytes, "b").unwrap().identity().unwrap(),
        id
    );
    // Wider image tokens change what slot attention reads: no growth keeps that.
    let wider_tokens = cfg
        .with_overrides(&[format!("feature_dim={}", 2 * cfg.feature_dim)])
        .unwrap();
    let Err(err) = a.reconfigured(&wider_tokens, 0, "m.safetensors") else {
        panic!("wider image tokens were accepted");
    };
    let err = err.to_string();
    assert!(err.starts_with("m.safetensors: "), "{err}");
    assert!(err.contains("does not match its config"), "{err}");
}

/// Rewrites a model file with changed tensors/metadata via the crate's writer.
fn rewrite(
    bytes: &[u8],
    edit: impl FnOnce(
        &mut std::collections::BTreeMap<String, (Vec<usize>, Vec<f32>)>,
        &mut std::collections::BTreeMap<String, String>,
    ),
) -> Vec<u8> {
    let file = colf::tensorfile::TensorFile::parse(bytes, "x").unwrap();
    let mut meta = file.metadata.clone();
    let mut tensors = std::collections::BTreeMap::new();
    for name in file.tensors.names() {
        let view = file.tensors.tensor(name).unwrap();
        let data: Vec<f32> = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        tensors.insert(name.to_string(), (view.shape().to_vec(), data));
    }
    edit(&mut tensors, &mut meta);
    let list: Vec<colf::tensorfile::F32Tensor> = tensors
        .iter()
        .map(|(n, (s, d))| colf::tensorfile::F32Tensor {
            name: n,
            shape: s.clone(),
            data: d,
        })
        .collect();
    colf::tensorfile::serialize_f32(&list, &meta)
}

fn load_err(bytes: &[u8]) -> String {
    match Colf::from_bytes(bytes, "bad.safetensors") {
        Ok(_) => panic!("a bad model file was accepted"),
        Err(e) => format!("{e:#}"),
    }
}

#[test]
fn bad_model_files_are_refused_with_clear_errors() {
    let cfg = tiny();
    let (bytes, _) = Colf::init(&cfg, 0).unwrap().to_bytes().unwrap();
    let fix_id = |t: &std::collections::BTreeMap<String, (Vec<usize>, Vec<f32>)>,
                  m: &mut std::collections::BTreeMap<String, String>| {
        let id = colf::model::checkpoint::identity(&m["config"], t);
        m.insert("identity".into(), id);
    };
    let cases: Vec<(Vec<u8>, &str)> = vec![
        (bytes[..bytes.len() / 2].to_vec(), "not a valid safetensors"),
        (
            rewrite(&bytes, |_, m| {
                m.insert("format".into(), "colf-codes/1".into());
            }),
            "not a colf model",
        ),
        (
            rewrite(&bytes, |_, m| {
                m.remove("config");
            }),
            "`config` is missing",
        ),
        (
            rewrite(&bytes, |t, _| {
                t.get_mut("compositor.gap_log_slope").unwrap().1[0] = 3.0;
            }),
            "does not match the file's contents",
        ),
        (
            rewrite(&bytes, |t, m| {
                t.get_mut("heads.color.layers.0.bias").unwrap().1[0] = f32::NAN;
                fix_id(t, m);
            }),
            "non-finite",
        ),
        (
            rewrite(&bytes, |t, m| {
                t.remove("encoder.up1.weight");
                fix_id(t, m);
            }),
            "tensor `encoder.up1.weight` is missing",
        ),
        (
            rewrite(&bytes, |t, m| {
                t.insert("stray".into(), (vec![1], vec![0.0]));
                fix_id(t, m);
            }),
            "unexpected tensor `stray`",
        ),
        (
            rewrite(&bytes, |t, m| {
                t.insert("compositor.gap_log_slope".into(), (vec![2], vec![0.0, 0.0]));
                fix_id(t, m);
            }),
            "`compositor.gap_log_slope` has shape [2], expected [1]",
        ),
    ];
    for (bad, want) in cases {
        let msg = load_err(&bad);
        assert!(msg.starts_with("bad.safetensors"), "{msg}");
        assert!(msg.contains(want), "expected `{want}` in: {msg}");
    }
}

#[test]
fn generated_light_field_weights_have_kaiming_scale() {
    let cfg = Config::small();
    let colf = Colf::init(&cfg, 0).unwrap();
    let mut rng = StdRng::seed_from_u64(9);
    let latents: Vec<f32> = (0..16 * cfg.slot_dim)
        .map(|_| rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut rng))
        .collect();
    let z = Tensor::from_vec(latents, (16, cfg.slot_dim), &Device::Cpu).unwrap();
    let layers = colf.model().hypernet_fg.forward(&z).unwrap();
    let dims = cfg.lfn_dims();
    for (l, layer) in layers.iter().enumerate() {
        let w = layer
            .weight
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let std = (w.iter().map(|v| v * v).sum::<f32>() / w.len() as f32).sqrt();
        let gain = if l + 1 == layers.len() {
            1.0
        } else {
            2f32.sqrt()
        };
        let kaiming = gain / (dims[l] as f32).sqrt();
        assert!(
            std > 0.6 * kaiming && std < 1.6 * kaiming,
            "layer {l}: std {std}, Kaiming {kaiming}"
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Any finite ordering values and shifts give finite weights summing to 1.
    #[test]
    fn compositor_weights_are_a_distribution(
        values in proptest::collection::vec((-1e6f32..1e6, 0f32..1e5), 1..40),
        scale_exp in -3i32..4,
    ) {
        let colf = Colf::init(&Config::small(), 0).unwrap();
        let s = values.len();
        let mult = 10f32.powi(scale_exp);
        let ordering: Vec<f32> = values.iter().map(|v| v.0 * mult).collect();
        let shift: Vec<f32> = values.iter().map(|v| v.1).collect();
        let dev = Device::Cpu;
        let ordering = Tensor::from_vec(ordering, (1, 1, s), &dev).unwrap();
        let shift = Tensor::from_vec(shift, (1, 1, s), &dev).unwrap();
        let out = colf.model().compositor.forward(&ordering, &shift).unwrap();
        let w = out.weights.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        prop_assert!(w.iter().all(|x| x.is_finite() && *x >= 0.0));
        let sum: f32 = w.iter().sum();
        prop_assert!((sum - 1.0).abs() < 1e-4, "sum {}", sum);
    }
}
