//! The fused decoder (`src/model/decode_kernel.rs`) against the composition of candle ops it
//! replaces (`ColfNet::decode_reference`, differentiated by candle's autograd): the same values
//! and the same gradients — of every model parameter, the slot latents and, when they are
//! differentiable, the rays — for every config knob in use, K = 0, 1, 7 and 60, and extreme
//! rays; and the same bytes whatever the thread count.

use candle_core::{DType, Device, Tensor, Var};
use colf::model::decode_kernel::RayMotion;
use colf::model::rays::MovingRays;
use colf::model::{Colf, Config, RayBatch, SceneRays};
use glam::{DMat4, DQuat, DVec3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use std::sync::Arc;

/// A small config with every knob of the default model on.
fn base() -> Config {
    Config {
        preset: "test".into(),
        encoder_size: 16,
        encoder_channels: 8,
        encoder_channels_low: 8,
        feature_dim: 8,
        slot_dim: 12,
        slot_mlp_hidden: 16,
        lfn_hidden: 24,
        lfn_hidden_layers: 2,
        lfn_features: 10,
        ray_fourier_freqs: 2,
        hypernet_hidden: 16,
        head_hidden: 12,
        head_hidden_layers: 1,
        compositor_hidden: 8,
        compositor_hidden_layers: 1,
        scene_scale: 8.0,
        background_reader: true,
        hypernet_rms_norm: true,
        attention_frames: true,
        fg_locality: 2.0,
        shadow_head: true,
        shadow_light: Some([30.0, 55.0]),
        ..Config::small()
    }
}

fn normal(rng: &mut StdRng, n: usize, scale: f32) -> Vec<f32> {
    (0..n)
        .map(|_| {
            let v: f64 = StandardNormal.sample(rng);
            scale * v as f32
        })
        .collect::<Vec<f32>>()
}

/// A model whose every parameter is perturbed away from its initialisation (where the shadow
/// head's weight is 0 and the ordering head's output near 0, which would hide errors).
fn model(cfg: &Config, seed: u64) -> Colf {
    let mut colf = Colf::init(cfg, seed).unwrap();
    let mut rng = StdRng::seed_from_u64(seed + 100);
    let names: Vec<(String, Tensor)> = colf
        .parameters()
        .iter()
        .map(|(n, t)| (n.clone(), t.clone()))
        .collect();
    for (name, t) in names {
        let scale = if name.starts_with("heads.") || name.starts_with("compositor.") {
            0.3
        } else {
            0.02
        };
        let noise = Tensor::from_vec(
            normal(&mut rng, t.elem_count(), scale),
            t.shape(),
            &Device::Cpu,
        )
        .unwrap();
        colf = colf.with_tensor(&name, (t + noise).unwrap()).unwrap();
    }
    colf.into_trainable().unwrap()
}

/// Rays of one scene: `r` rays from cameras around the origin (a few far away when `extreme`,
/// every seventh looking up, off the ground, when `sky`), and K slot frames (rotated and
/// translated; far away when `extreme`).
fn scene(
    rng: &mut StdRng,
    k: usize,
    r: usize,
    (extreme, sky): (bool, bool),
) -> (Vec<DMat4>, Vec<DVec3>, Vec<DVec3>) {
    let frames = (0..k)
        .map(|i| {
            let far = if extreme && i % 2 == 1 { 1e4 } else { 1.0 };
            let t = DVec3::new(
                rng.random_range(-3.0..3.0) * far,
                rng.random_range(-3.0..3.0),
                rng.random_range(0.0..1.0),
            );
            DMat4::from_rotation_translation(DQuat::from_rotation_z(rng.random_range(0.0..6.0)), t)
        })
        .collect();
    let (mut origins, mut dirs) = (Vec::new(), Vec::new());
    for i in 0..r {
        let az: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        let dist = if extreme && i % 5 == 0 { 3e4 } else { 12.0 };
        let eye = DVec3::new(az.cos() * dist * 0.77, az.sin() * dist * 0.77, dist * 0.64);
        let look = DVec3::new(
            rng.random_range(-3.0..3.0),
            rng.random_range(-3.0..3.0),
            0.0,
        );
        origins.push(eye);
        let dir = look - eye;
        dirs.push(if sky && i % 7 == 3 {
            DVec3::new(dir.x, dir.y, -dir.z)
        } else {
            dir
        });
    }
    (frames, origins, dirs)
}

/// The rays of `b` scenes from [`scene`], encoded.
fn random_batch(
    cfg: &Config,
    rng: &mut StdRng,
    b: usize,
    k: usize,
    r: usize,
    (extreme, sky): (bool, bool),
) -> RayBatch {
    let scenes: Vec<_> = (0..b).map(|_| scene(rng, k, r, (extreme, sky))).collect();
    let scene_rays: Vec<SceneRays> = scenes
        .iter()
        .map(|(f, o, dir)| SceneRays {
            slot_to_world: f,
            origins: o,
            dirs: dir,
        })
        .collect();
    RayBatch::new(cfg, &scene_rays, &Device::Cpu).unwrap()
}

struct Case {
    cfg: Config,
    k: usize,
    scenes: usize,
    rays: usize,
    extreme: bool,
    /// Some rays look up, off the ground (they cast no shadow line).
    sky: bool,
    /// Make the rays differentiable (as refinement with moving frames does).
    ray_grads: bool,
}

/// Every output of a decode, and the gradients of a loss on all of them.
struct Run {
    outputs: Vec<(String, Tensor)>,
    grads: Vec<(String, Tensor)>,
}

fn run(case: &Case, reference: bool) -> Run {
    let colf = model(&case.cfg, 7);
    let mut net = colf.model().clone();
    net.reference_decoder = reference;
    let (b, k, d) = (case.scenes, case.k, case.cfg.slot_dim);
    let mut rng = StdRng::seed_from_u64(11);
    let fg = Var::from_vec(normal(&mut rng, b * k * d, 1.0), (b, k, d), &Device::Cpu).unwrap();
    let bg = Var::from_vec(normal(&mut rng, b * d, 1.0), (b, d), &Device::Cpu).unwrap();
    let fields = net.prepare(fg.as_tensor(), bg.as_tensor()).unwrap();
    let mut rays = random_batch(
        &case.cfg,
        &mut rng,
        b,
        k,
        case.rays,
        (case.extreme, case.sky),
    );
    let mut ray_vars = Vec::new();
    if case.ray_grads {
        let coords = Var::from_tensor(&rays.coords).unwrap();
        let shift = Var::from_tensor(&rays.shift).unwrap();
        rays.coords = coords.as_tensor().clone();
        rays.shift = shift.as_tensor().clone();
        ray_vars.push(("rays.coords".to_string(), coords));
        ray_vars.push(("rays.shift".to_string(), shift));
        if let Some((lines, _)) = rays.shadow_lines.as_mut() {
            let v = Var::from_tensor(lines).unwrap();
            *lines = v.as_tensor().clone();
            ray_vars.push(("rays.shadow_lines".to_string(), v));
        }
    }
    let out = net.decode(&fields, &rays).unwrap();
    let mut outputs = vec![
        ("rgb".to_string(), out.rgb.clone()),
        ("weights".to_string(), out.weights.clone()),
        ("log_weights".to_string(), out.log_weights.clone()),
        ("colors".to_string(), out.colors.clone()),
        ("ordering".to_string(), out.ordering.clone()),
    ];
    if let Some(s) = &out.shadow {
        outputs.push(("shadow".to_string(), s.clone()));
    }
    // A loss that reads every output with fixed random weights.
    let mut wrng = StdRng::seed_from_u64(3);
    let mut loss = Tensor::zeros((), DType::F32, &Device::Cpu).unwrap();
    for (name, t) in &outputs {
        let scale = if name == "ordering" { 0.01 } else { 1.0 };
        let w = Tensor::from_vec(
            normal(&mut wrng, t.elem_count(), scale),
            t.shape(),
            &Device::Cpu,
        )
        .unwrap();
        loss = (loss + (t * w).unwrap().sum_all().unwrap()).unwrap();
    }
    let grads = loss.backward().unwrap();
    let mut named: Vec<(String, Var)> = colf.named_vars();
    named.push(("latents.fg".into(), fg));
    named.push(("latents.bg".into(), bg));
    named.extend(ray_vars);
    let grads = named
        .into_iter()
        .filter_map(|(n, v)| grads.get(v.as_tensor()).map(|g| (n, g.clone())))
        .collect();
    Run { outputs, grads }
}

fn norm(t: &Tensor) -> f32 {
    t.sqr()
        .unwrap()
        .sum_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
        .sqrt()
}

/// ‖a − b‖ / ‖b‖ (absolute below a norm of 1e-6).
fn relative_error(a: &Tensor, b: &Tensor) -> f32 {
    let diff = norm(&(a - b).unwrap());
    diff / norm(b).max(1e-6)
}

fn check(case: Case) {
    let fused = run(&case, false);
    let reference = run(&case, true);
    let what = format!("K = {}, {:?}", case.k, case.cfg);
    for ((name, a), (_, b)) in fused.outputs.iter().zip(&reference.outputs) {
        assert_eq!(a.dims(), b.dims(), "{name}");
        // A slot absent from a ray (beyond `slot_reach`) has ordering +∞ and log-weight −∞
        // in both; those entries must agree exactly, the rest are compared below.
        let (a, b) = (
            &finite_where_equal(a, b, name),
            &finite_where_equal(b, a, name),
        );
        // Relative, or absolute on outputs whose values are all tiny: the reference's softplus,
        // ln(1 + e^−|x|) in f32, loses the σ of 1e-4 and below that the kernel's ln_1p keeps.
        let scale = norm(b).max((b.elem_count() as f32).sqrt());
        let err = norm(&(a - b).unwrap()) / scale;
        assert!(err < 1e-5, "output {name}: error {err:e} ({what})");
    }
    // A parameter the kernel hands an all-zero gradient (the shadow head with K = 0) may get
    // none from the reference: a missing gradient counts as zero.
    let mut checked = 0;
    let names: std::collections::BTreeSet<&String> = fused
        .grads
        .iter()
        .chain(&reference.grads)
        .map(|(n, _)| n)
        .collect();
    let find = |run: &Run, name: &str| {
        run.grads
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, g)| g.clone())
    };
    for name in names {
        let (a, b) = match (find(&fused, name), find(&reference, name)) {
            (Some(a), Some(b)) => (a, b),
            (Some(a), None) => (a.clone(), a.zeros_like().unwrap()),
            (None, Some(b)) => (b.zeros_like().unwrap(), b),
            (None, None) => unreachable!(),
        };
        let err = relative_error(&a, &b);
        assert!(
            err < 1e-4,
            "gradient of {name}: relative error {err:e} ({what})"
        );
        checked += 1;
    }
    assert!(checked > 20, "{checked} gradients compared");
}

/// `a` with its non-finite entries set to 0, after checking that `b` has the same non-finite
/// values at the same places.
fn finite_where_equal(a: &Tensor, b: &Tensor, name: &str) -> Tensor {
    let (va, vb) = (
        a.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        b.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
    );
    let out: Vec<f32> = va
        .iter()
        .zip(&vb)
        .map(|(x, y)| {
            if x.is_finite() {
                *x
            } else {
                assert_eq!(x.to_bits(), y.to_bits(), "output {name}: {x} against {y}");
                0.0
            }
        })
        .collect();
    Tensor::from_vec(out, a.shape(), &Device::Cpu).unwrap()
}

fn case(cfg: Config, k: usize) -> Case {
    Case {
        cfg,
        k,
        scenes: 2,
        rays: 150,
        extreme: false,
        sky: false,
        ray_grads: false,
    }
}

#[test]
fn default_knobs_with_k_0_1_7() {
    for k in [0, 1, 7] {
        check(case(base(), k));
    }
}

#[test]
fn sixty_slots() {
    check(Case {
        scenes: 1,
        rays: 70,
        ..case(base(), 60)
    });
}

#[test]
fn extreme_rays_and_frames() {
    check(Case {
        extreme: true,
        ..case(base(), 7)
    });
}

#[test]
fn shadows_on_the_ray_without_a_light() {
    check(case(
        Config {
            shadow_light: None,
            ..base()
        },
        3,
    ));
}

#[test]
fn no_shadows_no_fourier_features_no_locality() {
    check(case(
        Config {
            shadow_head: false,
            shadow_light: None,
            ray_fourier_freqs: 0,
            fg_locality: 0.0,
            attention_frames: false,
            background_reader: false,
            ..base()
        },
        4,
    ));
}

#[test]
fn a_static_background_and_deeper_heads() {
    check(case(
        Config {
            zero_background: true,
            static_background: true,
            background_reader: false,
            head_hidden_layers: 3,
            compositor_hidden_layers: 3,
            lfn_hidden_layers: 3,
            ..base()
        },
        5,
    ));
}

/// [`check`] with K = 1 and 7 and some rays off the ground, then with differentiable rays.
fn check_with_rays_off_the_ground(cfg: &Config) {
    for k in [1, 7] {
        check(Case {
            sky: true,
            ..case(cfg.clone(), k)
        });
    }
    check(Case {
        scenes: 1,
        sky: true,
        ray_grads: true,
        ..case(cfg.clone(), 6)
    });
}

/// With `shadow_reach`, shadow lines beyond it and rays off the ground are left out of the
/// kernel's shadow pass: the same values and gradients as the reference, which masks σ.
#[test]
fn shadow_lines_within_a_reach_and_rays_off_the_ground() {
    check_with_rays_off_the_ground(&Config {
        shadow_reach: 2.5,
        ..base()
    });
    check(Case {
        sky: true,
        ..case(base(), 5)
    });
}

/// The reach only removes shadow: σ within it is the unbounded model's, beyond it 0, and
/// about half of the random lines lie beyond 2.5 units here (so the test means something).
#[test]
fn a_shadow_reach_zeroes_only_the_far_lines() {
    let bounded = Config {
        shadow_reach: 2.5,
        ..base()
    };
    let shadow = |cfg: &Config| {
        let out = run(&case(cfg.clone(), 7), false);
        let (_, t) = out
            .outputs
            .iter()
            .find(|(n, _)| n == "shadow")
            .unwrap()
            .clone();
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    };
    let (free, near) = (shadow(&base()), shadow(&bounded));
    let zeroed = near.iter().filter(|&&v| v == 0.0).count() as f32 / near.len() as f32;
    assert!((0.2..0.8).contains(&zeroed), "{zeroed} of the σ zeroed");
    for (a, b) in near.iter().zip(&free) {
        assert!(
            *a == 0.0 || (a - b).abs() <= 1e-6 * b.abs().max(1.0),
            "{a} vs {b}"
        );
    }
}

/// With `slot_reach`, a foreground slot is absent from the rays beyond it: the kernel leaves
/// its light field out there, the reference masks it (ordering +∞, weight 0, no colour, no
/// shadow, no gradient); the same values and gradients, with shadows on lines or on the ray,
/// with a shadow reach beside it, rays off the ground, extreme rays and differentiable rays.
#[test]
fn slots_within_a_reach() {
    let reach = Config {
        slot_reach: 2.5,
        ..base()
    };
    check_with_rays_off_the_ground(&reach);
    check(Case {
        extreme: true,
        ..case(reach.clone(), 7)
    });
    check(case(
        Config {
            shadow_reach: 2.0,
            ..reach.clone()
        },
        5,
    ));
    check(case(
        Config {
            shadow_light: None,
            ..reach
        },
        5,
    ));
}

/// A slot absent from a ray has weight 0 and ordering +∞ there, and about half of the random
/// (ray, slot) pairs lie beyond 2.5 units here (so the test means something); where a slot is
/// present its colour is the unbounded model's.
#[test]
fn a_slot_reach_leaves_out_only_the_far_slots() {
    let bounded = Config {
        slot_reach: 2.5,
        ..base()
    };
    let output = |cfg: &Config, name: &str| {
        let out = run(&case(cfg.clone(), 7), false);
        let (_, t) = out.outputs.iter().find(|(n, _)| n == name).unwrap().clone();
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    };
    let (weights, ordering) = (output(&bounded, "weights"), output(&bounded, "ordering"));
    let fg: Vec<usize> = (0..weights.len()).filter(|i| i % 8 != 0).collect();
    let absent: Vec<usize> = fg
        .iter()
        .copied()
        .filter(|&i| ordering[i] == f32::INFINITY)
        .collect();
    let share = absent.len() as f32 / fg.len() as f32;
    assert!((0.2..0.8).contains(&share), "{share} of the pairs absent");
    assert!(absent.iter().all(|&i| weights[i] == 0.0));
    assert!((0..weights.len())
        .step_by(8)
        .all(|i| ordering[i].is_finite()));
    let (near, free) = (output(&bounded, "colors"), output(&base(), "colors"));
    for (i, (a, b)) in near.iter().zip(&free).enumerate() {
        // The background's colour is darkened by the shadows, which the reach changes.
        if i / 3 % 8 == 0 {
            continue;
        }
        let present = ordering[i / 3].is_finite();
        assert!(
            if present {
                (a - b).abs() <= 1e-6
            } else {
                *a == 0.0
            },
            "{a} vs {b}"
        );
    }
}

/// Floor features on the background (`floor_fourier_freqs`): its extra input columns, zeros in
/// the slots' rows, on the shadow lines and on rays off the ground; the same values and
/// gradients (of the rays' floor columns too when they are differentiable), with slots within
/// a reach, and on a static background.
#[test]
fn floor_features_on_the_background() {
    let floor = Config {
        floor_fourier_freqs: 3,
        ..base()
    };
    check_with_rays_off_the_ground(&floor);
    check(Case {
        sky: true,
        ..case(
            Config {
                slot_reach: 2.5,
                ..floor.clone()
            },
            5,
        )
    });
    check(Case {
        sky: true,
        ..case(
            Config {
                zero_background: true,
                static_background: true,
                background_reader: false,
                ray_fourier_freqs: 0,
                ..floor
            },
            3,
        )
    });
}

#[test]
fn differentiable_rays_as_in_refinement() {
    check(Case {
        scenes: 1,
        ray_grads: true,
        ..case(base(), 6)
    });
}

/// The kernel's result does not depend on the number of threads: the same bytes on 1 and 2.
#[test]
fn same_bytes_whatever_the_thread_count() {
    // With and without a shadow reach (whose shadow rows are gathered per field), some rays
    // off the ground.
    for cfg in [
        base(),
        Config {
            shadow_reach: 2.5,
            ..base()
        },
        Config {
            slot_reach: 2.5,
            ..base()
        },
    ] {
        same_bytes_on_1_and_2_threads(&cfg);
    }
}

fn same_bytes_on_1_and_2_threads(cfg: &Config) {
    let bytes = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let r = run(
                &Case {
                    rays: 300,
                    sky: true,
                    ..case(cfg.clone(), 7)
                },
                false,
            );
            r.outputs
                .iter()
                .chain(&r.grads)
                .flat_map(|(_, t)| t.flatten_all().unwrap().to_vec1::<f32>().unwrap())
                .map(f32::to_bits)
                .collect::<Vec<u32>>()
        })
    };
    assert_eq!(bytes(1), bytes(2));
}

/// With a support, a field absent from a ray decodes as a field pushed infinitely far behind
/// every other one on that ray (without shadows, which an absent field does not cast): the
/// same colours, weights and gradients as the full decode with those fields' ordering shifts
/// raised by 10⁶, where their weight underflows to exactly 0.
#[test]
fn a_support_leaves_out_exactly_the_fields_it_drops() {
    let cfg = Config {
        shadow_head: false,
        shadow_light: None,
        ..base()
    };
    let colf = model(&cfg, 9);
    let net = colf.model().clone();
    let (b, k, r, d) = (2usize, 5usize, 140usize, cfg.slot_dim);
    let s = 1 + k;
    let mut rng = StdRng::seed_from_u64(4);
    let fg = Var::from_vec(normal(&mut rng, b * k * d, 1.0), (b, k, d), &Device::Cpu).unwrap();
    let bg = Var::from_vec(normal(&mut rng, b * d, 1.0), (b, d), &Device::Cpu).unwrap();
    let rays = random_batch(&cfg, &mut rng, b, k, r, (false, false));
    // Field s of scene b keeps the rays where (ray + 3·s + b) % 4 != 0, the background all.
    let keeps = |bi: usize, si: usize, ri: usize| si == 0 || !(ri + 3 * si + bi).is_multiple_of(4);
    let support: Vec<Vec<u32>> = (0..b * s)
        .map(|u| {
            (0..r)
                .filter(|&ri| keeps(u / s, u % s, ri))
                .map(|ri| ri as u32)
                .collect()
        })
        .collect();
    let mut shift = rays.shift.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    for bi in 0..b {
        for ri in 0..r {
            for si in 0..s {
                if !keeps(bi, si, ri) {
                    shift[(bi * r + ri) * s + si] += 1e6;
                }
            }
        }
    }
    let pushed = RayBatch {
        shift: Tensor::from_vec(shift, (b, r, s), &Device::Cpu).unwrap(),
        coords: rays.coords.clone(),
        shadow_lines: None,
        base: rays.base.clone(),
        scenes: b,
        fields: s,
        rays: r,
        motion: None,
    };
    let target =
        Tensor::from_vec(normal(&mut rng, b * r * 3, 0.3), (b, r, 3), &Device::Cpu).unwrap();
    let run = |sparse: bool| {
        let fields = net.prepare(fg.as_tensor(), bg.as_tensor()).unwrap();
        let out = if sparse {
            net.decode_with_support(&fields, &rays, support.clone())
                .unwrap()
        } else {
            net.decode(&fields, &pushed).unwrap()
        };
        let loss = (&out.rgb - &target)
            .unwrap()
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap();
        let grads = loss.backward().unwrap();
        let mut named = colf.named_vars();
        named.push(("latents.fg".into(), fg.clone()));
        named.push(("latents.bg".into(), bg.clone()));
        let g: Vec<(String, Tensor)> = named
            .into_iter()
            .filter_map(|(n, v)| grads.get(v.as_tensor()).map(|g| (n, g.clone())))
            .collect();
        (out.rgb, out.weights, g)
    };
    let (rgb_sparse, w_sparse, g_sparse) = run(true);
    let (rgb_dense, w_dense, g_dense) = run(false);
    assert!(relative_error(&rgb_sparse, &rgb_dense) < 1e-6);
    assert!(relative_error(&w_sparse, &w_dense) < 1e-6);
    assert_eq!(g_sparse.len(), g_dense.len());
    for ((name, a), (_, b)) in g_sparse.iter().zip(&g_dense) {
        let err = relative_error(a, b);
        assert!(err < 1e-4, "gradient of {name}: relative error {err:e}");
    }
    // The dropped fields really are absent: weight exactly 0 where dropped.
    let w = w_sparse.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    for bi in 0..b {
        for ri in 0..r {
            for si in 0..s {
                if !keeps(bi, si, ri) {
                    assert_eq!(w[(bi * r + ri) * s + si], 0.0);
                }
            }
        }
    }
}

/// A support that keeps every ray decodes exactly as no support, shadows, shadow lines and
/// differentiable rays included (the gathered rows and the scattered ray gradients line up).
#[test]
fn a_full_support_changes_nothing() {
    let cfg = base();
    let colf = model(&cfg, 13);
    let net = colf.model().clone();
    let (k, r, d) = (4usize, 150usize, cfg.slot_dim);
    let mut rng = StdRng::seed_from_u64(8);
    let fg = Var::from_vec(normal(&mut rng, k * d, 1.0), (1, k, d), &Device::Cpu).unwrap();
    let bg = Var::from_vec(normal(&mut rng, d, 1.0), (1, d), &Device::Cpu).unwrap();
    let (frames, o, dir) = scene(&mut rng, k, r, (false, false));
    let base_rays = RayBatch::new(
        &cfg,
        &[SceneRays {
            slot_to_world: &frames,
            origins: &o,
            dirs: &dir,
        }],
        &Device::Cpu,
    )
    .unwrap();
    let run = |sparse: bool| {
        let coords = Var::from_tensor(&base_rays.coords).unwrap();
        let shift = Var::from_tensor(&base_rays.shift).unwrap();
        let (lines, ground) = base_rays.shadow_lines.clone().unwrap();
        let lines = Var::from_tensor(&lines).unwrap();
        let rays = RayBatch {
            coords: coords.as_tensor().clone(),
            shift: shift.as_tensor().clone(),
            shadow_lines: Some((lines.as_tensor().clone(), ground)),
            base: base_rays.base.clone(),
            scenes: 1,
            fields: 1 + k,
            rays: r,
            motion: None,
        };
        let fields = net.prepare(fg.as_tensor(), bg.as_tensor()).unwrap();
        let out = if sparse {
            let all: Vec<u32> = (0..r as u32).collect();
            net.decode_with_support(&fields, &rays, vec![all; 1 + k])
                .unwrap()
        } else {
            net.decode(&fields, &rays).unwrap()
        };
        let loss = (out.rgb.sqr().unwrap().sum_all().unwrap() + out.log_weights.sum_all().unwrap())
            .unwrap();
        let grads = loss.backward().unwrap();
        [
            fg.as_tensor(),
            bg.as_tensor(),
            coords.as_tensor(),
            shift.as_tensor(),
            lines.as_tensor(),
        ]
        .iter()
        .map(|t| grads.get(t).unwrap().clone())
        .chain([out.rgb])
        .collect::<Vec<Tensor>>()
    };
    for (a, b) in run(true).iter().zip(&run(false)) {
        assert!(relative_error(a, b) < 1e-6, "{}", relative_error(a, b));
    }
}

/// Rays that move linearly with two offsets t: x(t) = x₀ + t₀·D₀ + t₁·D₁ for the coordinates,
/// the shadow lines and the shifts, each with its own random directions D.
#[derive(Debug)]
struct LinearMotion {
    coords: [Vec<f32>; 2],
    lines: [Vec<f32>; 2],
    shift: [Vec<f32>; 2],
    per_field: usize,
}

impl RayMotion for LinearMotion {
    fn offsets(&self) -> usize {
        2
    }

    fn field_gradient(
        &self,
        u: usize,
        coords: (&[f32], &[f32]),
        lines: Option<(&[f32], &[f32])>,
    ) -> Vec<f64> {
        let block = u * self.per_field..(u + 1) * self.per_field;
        let dot = |g: &[f32], d: &[f32]| g.iter().zip(d).map(|(a, b)| (a * b) as f64).sum::<f64>();
        (0..2)
            .map(|n| {
                dot(coords.1, &self.coords[n][block.clone()])
                    + lines.map_or(0.0, |(_, g)| dot(g, &self.lines[n][block.clone()]))
            })
            .collect()
    }

    fn shift_gradient(&self, d_shift: &[f32]) -> Vec<f64> {
        (0..2)
            .map(|n| {
                d_shift
                    .iter()
                    .zip(&self.shift[n])
                    .map(|(a, b)| (a * b) as f64)
                    .sum()
            })
            .collect()
    }
}

/// The kernel's gradient of moving rays' offsets (contracted inside its field passes) is the
/// gradient of the same rays written as candle functions of the offsets (the packed rays), for
/// two scenes of 7 slots, with shadow lines, with and without a support; the values agree.
#[test]
fn moving_rays_give_the_packed_rays_gradients() {
    let cfg = base();
    let colf = model(&cfg, 21);
    let net = colf.model().clone();
    let (b, k, r, d) = (2usize, 7usize, 90usize, cfg.slot_dim);
    let s = 1 + k;
    let mut rng = StdRng::seed_from_u64(12);
    let fg = Var::from_vec(normal(&mut rng, b * k * d, 1.0), (b, k, d), &Device::Cpu).unwrap();
    let bg = Var::from_vec(normal(&mut rng, b * d, 1.0), (b, d), &Device::Cpu).unwrap();
    let base_rays = random_batch(&cfg, &mut rng, b, k, r, (false, true));
    let (lines0, ground) = base_rays.shadow_lines.clone().unwrap();
    let n_coords = base_rays.coords.elem_count();
    let mut directions = |n: usize| [normal(&mut rng, n, 0.1), normal(&mut rng, n, 0.1)];
    let motion = Arc::new(LinearMotion {
        coords: directions(n_coords),
        lines: directions(n_coords),
        shift: directions(b * r * s),
        per_field: r * cfg.ray_input_dim(),
    });
    // Field 3 of scene 0 and field 5 of scene 1 on every other ray only.
    let mut support: Vec<Vec<u32>> = vec![(0..r as u32).collect(); b * s];
    support[3] = (0..r as u32).step_by(2).collect();
    support[s + 5] = (1..r as u32).step_by(2).collect();
    for sparse in [false, true] {
        let run = |moving: bool| {
            let offsets = Var::zeros(2, DType::F32, &Device::Cpu).unwrap();
            let t = offsets.as_tensor();
            let moved = |x: &Tensor, dirs: &[Vec<f32>; 2]| {
                let mut x = x.clone();
                for (n, dir) in dirs.iter().enumerate() {
                    let dir = Tensor::from_vec(dir.clone(), x.shape(), &Device::Cpu).unwrap();
                    let tn = t.narrow(0, n, 1).unwrap().broadcast_as(x.shape()).unwrap();
                    x = (x + (dir * tn).unwrap()).unwrap();
                }
                x
            };
            let rays = RayBatch {
                coords: base_rays.coords.clone(),
                shift: base_rays.shift.clone(),
                shadow_lines: Some((lines0.clone(), ground.clone())),
                base: base_rays.base.clone(),
                scenes: b,
                fields: s,
                rays: r,
                motion: moving.then(|| MovingRays {
                    offsets: t.clone(),
                    motion: motion.clone(),
                }),
            };
            let rays = if moving {
                rays
            } else {
                RayBatch {
                    coords: moved(&rays.coords, &motion.coords),
                    shift: moved(&rays.shift, &motion.shift),
                    shadow_lines: Some((moved(&lines0, &motion.lines), ground.clone())),
                    ..rays
                }
            };
            let fields = net.prepare(fg.as_tensor(), bg.as_tensor()).unwrap();
            let out = if sparse {
                net.decode_with_support(&fields, &rays, support.clone())
                    .unwrap()
            } else {
                net.decode(&fields, &rays).unwrap()
            };
            let loss = (out.rgb.sqr().unwrap().sum_all().unwrap()
                + out.log_weights.exp().unwrap().sum_all().unwrap())
            .unwrap();
            let grads = loss.backward().unwrap();
            [t, fg.as_tensor(), bg.as_tensor()]
                .iter()
                .map(|t| grads.get(t).unwrap().clone())
                .chain([out.rgb])
                .collect::<Vec<Tensor>>()
        };
        let (moving, packed) = (run(true), run(false));
        assert!(norm(&packed[0]) > 1e-3, "the offsets must carry gradient");
        for (a, b) in moving.iter().zip(&packed) {
            assert!(relative_error(a, b) < 1e-5, "{}", relative_error(a, b));
        }
    }
}
