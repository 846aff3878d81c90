//! `make bench`: speed and memory of colf on this machine, as a table on stdout and one JSON
//! object per measurement in `target/bench/bench.json`.
//!
//! Each measurement runs in a fresh child process (this program with `--one SPEC`), so its peak
//! resident memory (VmHWM) is its own. Timings are medians of repeated runs after a warm-up.
//! FLOPs are counted analytically from the model config (2 per multiply-add of every matmul on
//! the per-ray path: light field, heads, compositor; for the volumetric baseline, every layer
//! per sample and slot, its latent columns folded into a per-slot bias as the renderer does), so
//! achieved GFLOP/s and the ratio to the measured matmul peak say how efficiently the hardware
//! is used: "of peak" divides by the best wall-clock matmul rate of this run (both cores, when
//! the other jobs let us have them), "of peak per CPU-s" divides work per CPU-second by the best
//! per-CPU-second rate of a matmul (one thread, or both), which other jobs on the machine do not
//! distort. Renders go through `colf::render::fast` as `colf-render` does; one row measures the
//! candle path (`Colf::render_rays`, what training uses) for comparison. Measurements that take
//! longer than 2 s are run once (no warm-up).

use anyhow::{bail, Context, Result};
use colf::model::{Colf, Config};
use glam::{DMat4, DVec3};
use serde_json::{json, Value};
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}

/// Peak resident memory of this process so far, MiB.
fn peak_rss_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|kb| kb.parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// Multiply-adds ×2 of one ray through one field: light field, colour and ordering heads,
/// compositor MLP.
fn lightfield_flops_per_ray_field(cfg: &Config) -> f64 {
    let mlp = |dims: &[usize]| dims.windows(2).map(|w| 2 * w[0] * w[1]).sum::<usize>();
    let lfn = mlp(&cfg.lfn_dims());
    let head = |out: usize| {
        let mut d = vec![cfg.lfn_features];
        d.extend(std::iter::repeat_n(cfg.head_hidden, cfg.head_hidden_layers));
        d.push(out);
        mlp(&d)
    };
    let mut comp = vec![2];
    comp.extend(std::iter::repeat_n(
        cfg.compositor_hidden,
        cfg.compositor_hidden_layers,
    ));
    comp.push(1);
    (lfn + head(3) + head(1) + mlp(&comp)) as f64
}

/// Multiply-adds ×2 of one sample of one slot through the volumetric decoder.
fn volumetric_flops_per_sample_slot(cfg: &Config) -> f64 {
    let v = cfg.volumetric.as_ref().expect("volumetric config");
    let (w, e, c) = (v.hidden, v.pos_dim(), v.color_hidden);
    let macs = e * w
        + (v.layers_before_skip - 1) * w * w
        + (w + e) * w
        + (v.layers_after_skip - 1) * w * w
        + w * (1 + c)
        + c * 3;
    2.0 * macs as f64
}

/// CPU time (user + system) of this process so far, seconds: on a machine shared with other
/// jobs, work per CPU-second measures efficiency where wall time measures luck.
fn cpu_seconds() -> f64 {
    // SAFETY: getrusage writes one `rusage` into the zeroed struct we own.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
    t(u.ru_utime) + t(u.ru_stime)
}

/// Times `f`: a warm-up run, then `reps` runs; a warm-up longer than 2 s is the only run.
/// Returns (median wall seconds, runs, CPU seconds per run over the measured runs).
fn time_median(reps: usize, mut f: impl FnMut() -> Result<()>) -> Result<(f64, usize, f64)> {
    let (t, c) = (Instant::now(), cpu_seconds());
    f()?;
    let first = t.elapsed().as_secs_f64();
    if first > 2.0 {
        return Ok((first, 1, cpu_seconds() - c));
    }
    let c = cpu_seconds();
    let times: Vec<f64> = (0..reps)
        .map(|_| {
            let t = Instant::now();
            f().map(|_| t.elapsed().as_secs_f64())
        })
        .collect::<Result<_>>()?;
    let cpu = (cpu_seconds() - c) / reps as f64;
    Ok((median(times), reps, cpu))
}

/// The rays of a 128² clevr567-like camera (distance 12.4, elevation 40°).
fn frame_rays(size: usize) -> (Vec<DVec3>, Vec<DVec3>) {
    let frame = colf::camera::Frame {
        file_path: None,
        intrinsics: colf::camera::Intrinsics::from_fov(size as u32, size as u32, 49.13),
        camera_to_world: colf::camera::look_at(
            colf::camera_path::spherical_position(DVec3::ZERO, 12.4, 30.0, 40.0),
            DVec3::ZERO,
            DVec3::Z,
        )
        .unwrap(),
    };
    frame.rays().iter().map(|r| (r.origin, r.direction)).unzip()
}

/// Deterministic pseudo-random values in [-1, 1].
fn noise(n: usize, seed: u64) -> Vec<f32> {
    let mut x = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (0..n)
        .map(|_| {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((x >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        })
        .collect()
}

fn measure_matmul() -> Result<Value> {
    use candle_core::{Device, Tensor};
    let dev = Device::Cpu;
    let (mut best, mut best_cpu) = (0.0f64, 0.0f64);
    for (m, k, n) in [(4096, 256, 256), (1024, 1024, 1024)] {
        let a = Tensor::from_vec(noise(m * k, 1), (m, k), &dev)?;
        let b = Tensor::from_vec(noise(k * n, 2), (k, n), &dev)?;
        let _ = a.matmul(&b)?;
        let flops = 2.0 * (m * k * n) as f64;
        for _ in 0..5 {
            let c0 = cpu_seconds();
            for _ in 0..8 {
                let t = Instant::now();
                let c = a.matmul(&b)?;
                let s = t.elapsed().as_secs_f64();
                drop(c);
                best = best.max(flops / s / 1e9);
            }
            best_cpu = best_cpu.max(8.0 * flops / (cpu_seconds() - c0) / 1e9);
        }
    }
    // One thread (no thread waits in the CPU time): the work a core does per CPU-second at
    // best, the fair reference on a machine shared with other jobs.
    let (m, k, n) = (4096usize, 256usize, 256usize);
    let (a, b) = (noise(m * k, 1), noise(k * n, 2));
    // The renderer's own dense layer (one `gemm` call, then a bias pass of m·n adds: 0.4 % of
    // the m·k·n multiply-adds), so the reference and the renders use the same kernel.
    let dense = colf::render::fast::HostDense {
        input: k,
        output: n,
        w: b,
        b: vec![0.0; n],
    };
    let mut c = vec![0f32; m * n];
    for _ in 0..5 {
        let c0 = cpu_seconds();
        for _ in 0..8 {
            dense.run(&a, k, m, &mut c, n, false);
        }
        let flops = 8.0 * 2.0 * (m * k * n) as f64;
        best_cpu = best_cpu.max(flops / (cpu_seconds() - c0) / 1e9);
    }
    Ok(
        json!({"what": "matmul peak (best of [4096,256]x[256,256] and 1024^3, f32)",
              "gflops": best, "gflops_per_cpu_s": best_cpu}),
    )
}

fn measure_render(
    preset: &str,
    slots: usize,
    size: usize,
    samples: Option<usize>,
    candle_path: bool,
    reps: usize,
) -> Result<Value> {
    let cfg = Config::preset(preset)?;
    let model = Colf::init(&cfg, 0)?;
    let d = cfg.slot_dim;
    let latents: Vec<Vec<f32>> = (0..slots).map(|k| noise(d, 10 + k as u64)).collect();
    let frames: Vec<DMat4> = (0..slots)
        .map(|k| {
            let a = k as f64 * 2.399;
            DMat4::from_translation(DVec3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.0))
        })
        .collect();
    let (origins, dirs) = frame_rays(size);
    let t = Instant::now();
    let prepared = model.prepare(&latents, &noise(d, 3))?;
    let renderer = colf::render::fast::FastRenderer::new(&model, &prepared, &frames)?;
    let prepare_ms = t.elapsed().as_secs_f64() * 1e3;
    let (s, runs, cpu) = time_median(reps, || {
        if candle_path {
            model.render_rays(&prepared, &frames, &origins, &dirs)?;
        } else {
            renderer.render(&origins, &dirs, samples, None)?;
        }
        Ok(())
    })?;
    let rays = (size * size) as f64;
    let fields = (slots + 1) as f64;
    let (flops, what, samples) = match &cfg.volumetric {
        Some(v) => {
            let n = samples.unwrap_or(v.samples);
            (
                volumetric_flops_per_sample_slot(&cfg) * rays * fields * n as f64,
                "render one frame (volumetric)",
                json!(n),
            )
        }
        None if candle_path => (
            lightfield_flops_per_ray_field(&cfg) * rays * fields,
            "render one frame (candle path)",
            Value::Null,
        ),
        None => (
            lightfield_flops_per_ray_field(&cfg) * rays * fields,
            "render one frame",
            Value::Null,
        ),
    };
    Ok(json!({
        "what": what, "preset": preset, "slots": slots, "resolution": size, "samples": samples,
        "ms": s * 1e3, "fps": 1.0 / s, "gflop_per_frame": flops / 1e9, "gflops": flops / s / 1e9,
        "gflops_per_cpu_s": flops / cpu / 1e9, "cpu_ms": cpu * 1e3,
        "prepare_ms": prepare_ms, "runs": runs, "peak_mib": peak_rss_mib(),
    }))
}

fn measure_encode(preset: &str, reps: usize) -> Result<Value> {
    let cfg = Config::preset(preset)?;
    let model = Colf::init(&cfg, 0)?;
    let image: Vec<f32> = noise(128 * 128 * 3, 5)
        .iter()
        .map(|v| 0.5 + 0.5 * v)
        .collect();
    let _ = model.encode(&image, 128, 128, 7, 0)?;
    let times: Vec<f64> = (0..reps)
        .map(|_| {
            let t = Instant::now();
            model
                .encode(&image, 128, 128, 7, 0)
                .map(|_| t.elapsed().as_secs_f64())
        })
        .collect::<Result<_>>()?;
    Ok(
        json!({"what": "encode one 128x128 image", "preset": preset, "slots": 7,
              "ms": median(times) * 1e3, "peak_mib": peak_rss_mib()}),
    )
}

/// The `paper` preset's decoder sizes as `--set` overrides of the default model's config (its
/// encoder, slot attention and knobs kept): the decoder issue 37 trains.
pub const PAPER_DECODER: [&str; 7] = [
    "lfn_hidden=256",
    "lfn_features=64",
    "head_hidden=128",
    "head_hidden_layers=3",
    "compositor_hidden=128",
    "compositor_hidden_layers=3",
    "hypernet_hidden=64",
];

/// A training step as `colf-train` runs it: the default model's own recipe (the bundled model
/// as init; 4 scenes × 4 views × 256 rays, K = 7, object proposals for both mask losses), or
/// (`paper`) the same with the decoder at the `paper` preset's sizes; through the fused decoder
/// or (`reference`) candle's autograd; with the model's `shadow_reach` and `slot_reach` set as
/// `reach` says.
fn measure_train(which: &str, reference: bool, reach: Reach, steps: u64) -> Result<Value> {
    use colf::train::trainer::{TrainOptions, Trainer};
    let dir = tempfile::tempdir()?;
    let synth = sibling_binary("colf-synth")?;
    let status = std::process::Command::new(&synth)
        .args(["--scenes", "16", "--seed", "1", "-q", "--out"])
        .arg(dir.path().join("data"))
        .status()
        .with_context(|| format!("running {}", synth.display()))?;
    if !status.success() {
        bail!("colf-synth failed");
    }
    let default = std::path::PathBuf::from("models/default.safetensors");
    let init = if which == "paper" {
        // The default model's config with the paper's decoder: a fresh model.
        let cfg = Colf::load(&default)?
            .config()
            .with_overrides(&PAPER_DECODER.map(String::from))?;
        let path = dir.path().join("paper-init.safetensors");
        Colf::init(&cfg, 0)?.save(&path)?;
        path
    } else {
        default
    };
    let opts = TrainOptions {
        data: dir.path().join("data"),
        out: dir.path().join("m.safetensors"),
        init: Some(init),
        steps,
        batch_scenes: 4,
        views_per_scene: 4,
        rays_per_view: 256,
        slots: None,
        lr: 5e-5,
        warmup: 10,
        mask_weight: 0.1,
        attention_mask_weight: 0.1,
        proposals: true,
        seed: 0,
        checkpoint_every: 0,
        keep_every: 0,
        eval_every: 0,
        eval_data: None,
        eval_scenes: 0,
        max_bad_steps: 10,
        reference_decoder: reference,
        config_overrides: reach.overrides(),
        ..TrainOptions::default()
    };
    let mut trainer = Trainer::new(opts, false)?;
    let _ = trainer.train_step()?; // warm-up
    let (c, t) = (cpu_seconds(), Instant::now());
    let logs: Vec<_> = (0..steps)
        .map(|_| trainer.train_step())
        .collect::<Result<_>>()?;
    let (wall, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
    let s = median(logs.iter().map(|l| l.seconds).collect());
    // The same steps without their time in the decode kernel: what a free decoder would leave.
    let rest = median(logs.iter().map(|l| l.seconds - l.decoder_s).collect());
    let path = if reference { "autograd" } else { "fused" };
    let spin = std::env::var("CANDLE_BARRIER_POOL_SPIN_LIMIT").unwrap_or_default();
    let threads = if spin == "25000" {
        ", candle's default pool spin"
    } else {
        ""
    };
    Ok(json!({
        "what": format!("training step ({path}{threads}{}; 4 scenes x 4 views x 256 rays, K=7, proposals)", reach.label()),
        "preset": which, "slots": 7, "runs": steps,
        "ms": s * 1e3, "steps_per_hour": 3600.0 / s, "cores_busy": cpu / wall,
        "rays_per_s": 4096.0 / s, "peak_mib": peak_rss_mib(),
        "rest_ms": (!reference).then_some(rest * 1e3)
    }))
}

/// The bounds a measurement's model has on where slots are evaluated (0: none): the shadow
/// lines' (`shadow_reach`) and the camera rays' (`slot_reach`).
#[derive(Clone, Copy, Debug, Default)]
struct Reach {
    shadow: f64,
    slots: f64,
}

impl Reach {
    /// From a measurement's spec: `reach` (the shadow reach) and `slot_reach`.
    fn of(spec: &Value) -> Reach {
        Reach {
            shadow: spec["reach"].as_f64().unwrap_or(0.0),
            slots: spec["slot_reach"].as_f64().unwrap_or(0.0),
        }
    }

    fn is_none(&self) -> bool {
        self.shadow == 0.0 && self.slots == 0.0
    }

    /// `--set shadow_reach=…` and `--set slot_reach=…` for the reaches > 0.
    fn overrides(&self) -> Vec<String> {
        let mut out = Vec::new();
        if self.shadow > 0.0 {
            out.push(format!("shadow_reach={}", self.shadow));
        }
        if self.slots > 0.0 {
            out.push(format!("slot_reach={}", self.slots));
        }
        out
    }

    /// A row's note of the reaches, empty without one.
    fn label(&self) -> String {
        let mut out = String::new();
        if self.shadow > 0.0 {
            out += &format!(", shadow reach {}", self.shadow);
        }
        if self.slots > 0.0 {
            out += &format!(", slot reach {}", self.slots);
        }
        out
    }
}

/// The config of a decoder measurement: the bundled default model's, or that with the `paper`
/// preset's decoder sizes ([`PAPER_DECODER`]).
fn decoder_config(which: &str) -> Result<Config> {
    let default = Colf::load(std::path::Path::new("models/default.safetensors"))?
        .config()
        .clone();
    Ok(match which {
        "default" => Config {
            inference: None,
            ..default
        },
        "paper" => Config {
            inference: None,
            ..default.with_overrides(&PAPER_DECODER.map(String::from))?
        },
        other => bail!("unknown decoder config {other}"),
    })
}

/// The decoder part of a training step — the rays encoded, the light fields, heads, shadows
/// and compositor, the colour and mask losses, and the backward down to the hypernetworks'
/// outputs — for 4 scenes × 4 views × 256 rays, K = 7, through the fused kernel or (with
/// `reference`) candle's autograd; with `shadow_reach` and `slot_reach` as `reach` says.
fn measure_decoder(which: &str, reference: bool, reach: Reach, reps: usize) -> Result<Value> {
    use candle_core::{Device, Tensor, Var};
    use colf::model::decode_kernel::DecodeShape;
    use colf::model::{RayBatch, SceneRays, SlotWeights};
    let cfg = decoder_config(which)?.with_overrides(&reach.overrides())?;
    let (b, k, r) = (4usize, 7usize, 1024usize);
    let colf = Colf::init(&cfg, 0)?.into_trainable()?;
    let mut net = colf.model().clone();
    net.reference_decoder = reference;
    let dev = Device::Cpu;
    let d = cfg.slot_dim;
    let fg = Tensor::from_vec(noise(b * k * d, 3), (b, k, d), &dev)?;
    let bg = Tensor::from_vec(noise(b * d, 4), (b, d), &dev)?;
    // The generated weights as leaves: the backward stops at the hypernetworks' outputs.
    let prepared = net.prepare(&fg, &bg)?;
    let mut leaves = Vec::new();
    let layers = prepared
        .layers
        .iter()
        .map(|l| {
            let (w, bias) = (Var::from_tensor(&l.weight)?, Var::from_tensor(&l.bias)?);
            let layer = colf::model::hypernet::GeneratedLayer {
                weight: w.as_tensor().clone(),
                bias: bias.as_tensor().clone(),
            };
            leaves.push(w);
            leaves.push(bias);
            Ok(layer)
        })
        .collect::<Result<Vec<_>>>()?;
    let fields = SlotWeights { layers };
    // Four views of each scene, 256 rays each, from a 64² clevr567 camera.
    let (origins, dirs) = frame_rays(64);
    let frames: Vec<DMat4> = (0..k)
        .map(|i| DMat4::from_translation(DVec3::new(i as f64 - 3.0, 0.5, 0.3)))
        .collect();
    let pick: Vec<usize> = (0..r).map(|i| (i * 997) % origins.len()).collect();
    let o: Vec<DVec3> = pick.iter().map(|&i| origins[i]).collect();
    let dv: Vec<DVec3> = pick.iter().map(|&i| dirs[i]).collect();
    let target = Tensor::from_vec(
        noise(b * r * 3, 5)
            .iter()
            .map(|v| 0.5 + 0.4 * v)
            .collect::<Vec<f32>>(),
        (b, r, 3),
        &dev,
    )?;
    let labels = Tensor::from_vec(
        (0..b * r)
            .map(|i| (i % (k + 1)) as u32)
            .collect::<Vec<u32>>(),
        (b * r, 1),
        &dev,
    )?;
    let step = || -> Result<()> {
        let scenes: Vec<SceneRays> = (0..b)
            .map(|_| SceneRays {
                slot_to_world: &frames,
                origins: &o,
                dirs: &dv,
            })
            .collect();
        let rays = RayBatch::new(&cfg, &scenes, &dev)?;
        let out = net.decode(&fields, &rays)?;
        let mse = (&out.rgb - &target)?.sqr()?.mean_all()?;
        let ce = out
            .log_weights
            .reshape((b * r, k + 1))?
            .gather(&labels, 1)?
            .mean_all()?
            .neg()?;
        let grads = (mse + (ce * 0.1)?)?.backward()?;
        if grads.get(leaves[0].as_tensor()).is_none() {
            bail!("no gradient reached the generated weights");
        }
        Ok(())
    };
    let (s, runs, cpu) = time_median(reps, step)?;
    let shape = DecodeShape::new(&cfg, b, 1 + k, r);
    let (fwd, bwd) = shape.macs(false);
    let gflop = 2.0 * (fwd + bwd) * 1e-9;
    let path = if reference { "autograd" } else { "fused" };
    let mut row = json!({
        "what": format!("decoder fwd+bwd of a training step ({path}{}; 4 scenes x 4 views x 256 rays, K=7)", reach.label()),
        "preset": which, "slots": k, "runs": runs,
        "ms": s * 1e3, "steps_per_hour": 3600.0 / s, "peak_mib": peak_rss_mib()
    });
    // With a reach the kernel skips work the count includes: no rate is claimed.
    if reach.is_none() {
        row["gflops"] = json!(gflop / s);
        row["gflops_per_cpu_s"] = json!(gflop / cpu);
    }
    Ok(row)
}

/// Flags of the half-length refinement measured against the default encoding
/// (docs/refinement.md, "The learning rates again"): the same scores on held-out scenes.
const HALF_REFINEMENT: [&str; 6] = [
    "--refine",
    "25",
    "--refine-lr",
    "0.02",
    "--refine-frame-lr",
    "0.015",
];

/// One held-out colf-synth scene (test split, seed 9) at `size`², in a folder that lives as long
/// as this value: what the encoding and model-file rows measure on.
struct BenchScene {
    dir: tempfile::TempDir,
}

impl BenchScene {
    fn new(size: usize) -> Result<BenchScene> {
        let dir = tempfile::tempdir()?;
        let synth = sibling_binary("colf-synth")?;
        let status = std::process::Command::new(&synth)
            .args([
                "--scenes", "1", "--seed", "9", "--split", "test", "-q", "--size",
            ])
            .arg(size.to_string())
            .arg("--out")
            .arg(dir.path())
            .status()
            .with_context(|| format!("running {}", synth.display()))?;
        if !status.success() {
            bail!("colf-synth failed");
        }
        Ok(BenchScene { dir })
    }

    /// View 0 as `model`'s encoder reads it, and the scene's cameras.
    fn view_0(&self, model: &Colf) -> Result<(colf::image_io::RgbImage32, colf::camera::Cameras)> {
        let scene = self.dir.path().join("scene_00000");
        let png = std::fs::read(scene.join("view_000.png"))?;
        let image = colf::image_io::decode_rgb_for_encoder(
            &png,
            "view_000.png",
            model.config().encoder_size as u32,
            colf::image_io::ENCODE_FULL_RES_PIXELS,
        )?;
        let cameras =
            colf::camera::Cameras::read(&scene.join("transforms.json").to_string_lossy())?;
        Ok((image, cameras))
    }
}

/// A frame of a model file as `colf-render` draws it: view 0 of the bench scene encoded in one
/// pass (`colf-encode --fast --slots SLOTS`), rendered exactly — with the slots' shadows and the
/// model's own reaches — from view 1, at the scene's `size`². Unlike the preset rows (fresh
/// weights, slots on a ring), this is the shipped model on slots where its encoder puts them, so
/// `slot_reach` leaves out what it would in use; no FLOP count, as that depends on the slots'
/// placement.
fn measure_model_render(path: &str, slots: usize, size: usize, reps: usize) -> Result<Value> {
    use clap::Parser;
    let scene = BenchScene::new(size)?;
    let model = Colf::load(std::path::Path::new(path))?;
    let (image, cameras) = scene.view_0(&model)?;
    let slot_flag = slots.to_string();
    let args = colf::cli::encode::EncodeArgs::try_parse_from([
        "colf-encode",
        "view_000.png",
        "--fast",
        "--slots",
        &slot_flag,
    ])?;
    let opts = colf::encode::EncodeOptions {
        camera: Some(cameras.frames[0].clone()),
        source: "view_000.png".into(),
        ..args.fit.encode_options(model.config(), None, 0)
    };
    let codes = colf::encode::encode_image(&model, &image, &opts)?;
    let prepared = colf::render::PreparedScene::new(&model, &codes, path)?;
    let frame = &cameras.frames[1];
    let (s, runs, cpu) = time_median(reps, || prepared.render_frame(&model, frame).map(|_| ()))?;
    Ok(json!({
        "what": format!("render one frame ({path}, one-pass encoding of a colf-synth scene)"),
        "preset": "model file", "slots": codes.slots.len(), "resolution": size,
        "ms": s * 1e3, "fps": 1.0 / s, "cpu_ms": cpu * 1e3, "runs": runs,
        "peak_mib": peak_rss_mib(),
    }))
}

/// The bundled default model.
const BUNDLED_MODEL: &str = "models/default.safetensors";

/// A model file's default encoding (its measured slots, tries and refinement, as `colf-encode`
/// with no flags, or with `HALF_REFINEMENT` when `half`) of view 0 of a colf-synth scene of
/// `size`², with the refinement through the fused decoder or (`reference`) candle's autograd.
/// Reports wall and CPU time. Rows of a model other than the bundled one name its path.
fn measure_default_encode(
    model_path: &str,
    size: usize,
    reference: bool,
    half: bool,
    reps: usize,
) -> Result<Value> {
    use clap::Parser;
    let scene = BenchScene::new(size)?;
    let mut model = Colf::load(std::path::Path::new(model_path))?;
    model.set_reference_decoder(reference);
    let (image, cameras) = scene.view_0(&model)?;
    let flags: &[&str] = if half { &HALF_REFINEMENT } else { &[] };
    let args = colf::cli::encode::EncodeArgs::try_parse_from(
        [&["colf-encode", "view_000.png"], flags].concat(),
    )?;
    let opts = colf::encode::EncodeOptions {
        camera: Some(cameras.frames[0].clone()),
        source: "view_000.png".into(),
        ..args.fit.encode_options(model.config(), None, 0)
    };
    let (s, runs, cpu) = time_median(reps.min(3), || {
        colf::encode::encode_image(&model, &image, &opts).map(|_| ())
    })?;
    let path = if reference { "autograd" } else { "fused" };
    let kind = if half {
        "half-length refinement"
    } else {
        "default encoding"
    };
    let what = if model_path == BUNDLED_MODEL {
        kind.to_string()
    } else {
        format!("{kind} of {model_path}")
    };
    let threads = rayon::current_num_threads();
    let plural = if threads == 1 { "" } else { "s" };
    Ok(json!({
        "what": format!("{what} ({} slots, {} tries, {} refinement steps, lr {} / frames {}; {path}; {threads} thread{plural})",
                        opts.num_slots, opts.tries, opts.refine.steps, opts.refine.lr,
                        opts.refine.frame_lr),
        "preset": "default", "resolution": size, "runs": runs,
        "ms": s * 1e3, "cpu_s": cpu, "peak_mib": peak_rss_mib()
    }))
}

/// A program built beside this example (`target/release/NAME`).
fn sibling_binary(name: &str) -> Result<std::path::PathBuf> {
    let exe = std::env::current_exe()?;
    exe.parent()
        .and_then(|p| p.parent())
        .map(|p| p.join(name))
        .context("the release folder")
}

fn run_one(spec: &Value) -> Result<Value> {
    let quick = spec["quick"].as_bool().unwrap_or(false);
    let reps = if quick { 2 } else { 5 };
    match spec["kind"].as_str() {
        Some("matmul") => measure_matmul(),
        Some("render") => measure_render(
            spec["preset"].as_str().unwrap_or("small"),
            spec["slots"].as_u64().unwrap_or(7) as usize,
            spec["size"].as_u64().unwrap_or(128) as usize,
            spec["samples"].as_u64().map(|n| n as usize),
            spec["candle"].as_bool().unwrap_or(false),
            reps,
        ),
        Some("encode") => measure_encode(spec["preset"].as_str().unwrap_or("small"), reps),
        Some("render-model") => measure_model_render(
            spec["model"]
                .as_str()
                .unwrap_or("models/default.safetensors"),
            spec["slots"].as_u64().unwrap_or(7) as usize,
            spec["size"].as_u64().unwrap_or(128) as usize,
            reps,
        ),
        Some("train") => measure_train(
            spec["preset"].as_str().unwrap_or("default"),
            spec["reference"].as_bool().unwrap_or(false),
            Reach::of(spec),
            if quick { 3 } else { 10 },
        ),
        Some("default-encode") => measure_default_encode(
            spec["model"].as_str().unwrap_or(BUNDLED_MODEL),
            spec["size"].as_u64().unwrap_or(64) as usize,
            spec["reference"].as_bool().unwrap_or(false),
            spec["half"].as_bool().unwrap_or(false),
            reps,
        ),
        Some("decoder") => measure_decoder(
            spec["preset"].as_str().unwrap_or("default"),
            spec["reference"].as_bool().unwrap_or(false),
            Reach::of(spec),
            reps,
        ),
        other => bail!("unknown measurement {other:?}"),
    }
}

/// The shadow reach of the trainer's `shadow reach` rows (world units): the one the room and
/// paper-sized runs train with (`docs/speed.md`).
const SHADOW_REACH: f64 = 3.0;

/// The slot reach of the `slot reach` rows (frame units): the one run p's p9 and the room runs
/// train with (`docs/speed.md`).
const SLOT_REACH: f64 = 3.0;

fn main() -> Result<()> {
    // As every colf program does (cli::run): keep freed tensor buffers instead of returning
    // them to the kernel, which is most of a training step's speed.
    colf::alloc::tune_for_tensors();
    colf::alloc::tune_thread_pools();
    let args: Vec<String> = std::env::args().collect();
    if args.len() == 3 && args[1] == "--one" {
        let spec: Value = serde_json::from_str(&args[2])?;
        println!("{}", run_one(&spec)?);
        return Ok(());
    }
    let quick = args.iter().any(|a| a == "--quick");
    let out = args
        .iter()
        .position(|a| a == "--out")
        .and_then(|i| args.get(i + 1).cloned())
        .unwrap_or_else(|| "target/bench/bench.json".into());
    let only_render = args.iter().any(|a| a == "--render-only");
    let only_train = args.iter().any(|a| a == "--train-only");
    // A model file to measure beside the bundled one (`--model PATH`): its frame and its default
    // encoding, each next to the bundled model's row, so their ratio comes from one run.
    let other_model = args
        .iter()
        .position(|a| a == "--model")
        .and_then(|i| args.get(i + 1).cloned());
    let mut specs = vec![json!({"kind": "matmul"})];
    if !only_render {
        // The trainer: the decoder part of a step and whole steps, fused and autograd side by
        // side; the autograd step also as it ran before (candle's default pool spin).
        // Each also with shadow lines kept within SHADOW_REACH of their slot (the models'
        // `shadow_reach`, which training can set).
        for preset in ["default", "paper"] {
            for reference in [false, true] {
                specs.push(json!({"kind": "decoder", "preset": preset, "reference": reference}));
            }
            specs.push(json!({"kind": "decoder", "preset": preset, "reach": SHADOW_REACH}));
            specs.push(
                json!({"kind": "decoder", "preset": preset, "reach": SHADOW_REACH,
                              "slot_reach": SLOT_REACH}),
            );
        }
        for preset in ["default", "paper"] {
            specs.push(json!({"kind": "train", "preset": preset}));
            specs.push(json!({"kind": "train", "preset": preset, "reference": true}));
            specs.push(json!({"kind": "train", "preset": preset, "reference": true,
                              "candle_spin": "25000"}));
            specs.push(json!({"kind": "train", "preset": preset, "reach": SHADOW_REACH}));
            specs.push(
                json!({"kind": "train", "preset": preset, "reach": SHADOW_REACH,
                              "slot_reach": SLOT_REACH}),
            );
        }
        for size in [64, 128] {
            for reference in [false, true] {
                specs.push(json!({"kind": "default-encode", "size": size, "reference": reference}));
            }
            specs.push(json!({"kind": "default-encode", "size": size, "half": true}));
            // The same on one thread: what a second core gives, as a ratio from this run.
            specs.push(json!({"kind": "default-encode", "size": size, "threads": 1}));
        }
        // Issue 37's encoding budget (1.5x the bundled model's CPU time) is read on these rows,
        // the bundled model's measured again after the other's.
        if let Some(model) = &other_model {
            specs
                .push(json!({"kind": "default-encode", "model": model, "size": 128, "threads": 1}));
            specs.push(json!({"kind": "default-encode", "size": 128, "threads": 1}));
        }
    }
    if !only_train {
        // The shipped model file (and any `--model PATH` given) as colf-render draws a 7-slot
        // frame: issue 37's frame-rate target is read on this row.
        let mut model_files = vec![BUNDLED_MODEL.to_string()];
        model_files.extend(other_model.clone());
        for model in model_files {
            specs.push(json!({"kind": "render-model", "model": model, "slots": 7, "size": 128}));
        }
        for preset in ["small", "paper"] {
            for slots in [2, 7, 60] {
                specs
                    .push(json!({"kind": "render", "preset": preset, "slots": slots, "size": 128}));
            }
            if !only_render {
                specs.push(json!({"kind": "encode", "preset": preset}));
            }
        }
        specs.push(
            json!({"kind": "render", "preset": "small", "slots": 7, "size": 128, "candle": true}),
        );
        for slots in [2, 7, 60] {
            for samples in [32, 64, 128] {
                specs.push(
                    json!({"kind": "render", "preset": "volumetric", "slots": slots,
                                  "size": 128, "samples": samples}),
                );
            }
        }
        if !only_render {
            specs.push(json!({"kind": "encode", "preset": "volumetric"}));
        }
    }
    let exe = std::env::current_exe()?;
    let mut results = Vec::new();
    let mut peak = f64::NAN;
    let mut peak_cpu = f64::NAN;
    for mut spec in specs {
        spec["quick"] = json!(quick);
        eprintln!("bench: {spec}");
        let mut command = std::process::Command::new(&exe);
        if let Some(spin) = spec["candle_spin"].as_str() {
            command.env("CANDLE_BARRIER_POOL_SPIN_LIMIT", spin);
        }
        if let Some(threads) = spec["threads"].as_u64() {
            command
                .env("RAYON_NUM_THREADS", threads.to_string())
                .env("CANDLE_NUM_THREADS", threads.to_string());
        }
        let child = command.arg("--one").arg(spec.to_string()).output()?;
        if !child.status.success() {
            bail!(
                "measurement {spec} failed: {}",
                String::from_utf8_lossy(&child.stderr)
            );
        }
        let mut row: Value = serde_json::from_slice(&child.stdout)?;
        if let Some(g) = row["gflops"].as_f64() {
            if row["what"]
                .as_str()
                .is_some_and(|w| w.starts_with("matmul"))
            {
                peak = g;
                peak_cpu = row["gflops_per_cpu_s"].as_f64().unwrap_or(f64::NAN);
            } else if peak.is_finite() {
                row["ratio_to_peak"] = json!(g / peak);
                if let Some(c) = row["gflops_per_cpu_s"].as_f64() {
                    row["cpu_ratio_to_peak"] = json!(c / peak_cpu);
                }
            }
        }
        results.push(row);
    }
    println!(
        "| what | preset | slots | res | samples | ms | FPS | steps/h | CPU s | GFLOP/s | of peak | GFLOP per CPU-s | of peak per CPU-s | peak MiB |"
    );
    println!(
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
    );
    let cell = |v: &Value, digits: usize| {
        v.as_f64()
            .map_or("".to_string(), |x| format!("{x:.digits$}"))
    };
    for r in &results {
        let pct = |v: &Value| {
            v.as_f64()
                .map_or(String::new(), |x| format!("{:.0} %", 100.0 * x))
        };
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            r["what"].as_str().unwrap_or(""),
            r["preset"].as_str().unwrap_or(""),
            r["slots"].as_u64().map_or(String::new(), |v| v.to_string()),
            r["resolution"]
                .as_u64()
                .map_or(String::new(), |v| format!("{v}²")),
            r["samples"]
                .as_u64()
                .map_or(String::new(), |v| v.to_string()),
            cell(&r["ms"], 1),
            cell(&r["fps"], 2),
            cell(&r["steps_per_hour"], 0),
            cell(&r["cpu_s"], 2),
            cell(&r["gflops"], 1),
            pct(&r["ratio_to_peak"]),
            cell(&r["gflops_per_cpu_s"], 1),
            pct(&r["cpu_ratio_to_peak"]),
            cell(&r["peak_mib"], 0),
        );
    }
    // Volumetric ÷ light field (small preset, same slot count): the side-by-side ratio.
    let lf_ms = |slots: u64| {
        results.iter().find_map(|r| {
            (r["what"] == "render one frame" && r["preset"] == "small" && r["slots"] == slots)
                .then(|| r["ms"].as_f64())
                .flatten()
        })
    };
    let mut ratios = Vec::new();
    for r in &results {
        if r["preset"] == "volumetric" && r["samples"].is_u64() {
            if let (Some(v), Some(lf)) = (r["ms"].as_f64(), lf_ms(r["slots"].as_u64().unwrap_or(0)))
            {
                ratios.push(format!(
                    "{} slots, {} samples: {:.1}x",
                    r["slots"],
                    r["samples"],
                    v / lf
                ));
            }
        }
    }
    if !ratios.is_empty() {
        println!(
            "\nvolumetric / light field (small) render time: {}",
            ratios.join("; ")
        );
    }
    // Fused ÷ autograd, from this run's rows.
    let find = |kind: &str, preset: &str, path: &str, extra: &str| {
        results.iter().find(|r| {
            let what = r["what"].as_str().unwrap_or("");
            what.starts_with(kind)
                && what.contains(path)
                && (extra.is_empty() || what.contains(extra))
                && (!what.contains("default pool spin") || !extra.is_empty())
                && r["preset"] == preset
        })
    };
    let ratio = |a: Option<&Value>, b: Option<&Value>, key: &str| {
        Some(b?[key].as_f64()? / a?[key].as_f64()?)
    };
    for preset in ["default", "paper"] {
        let fused = find("training step", preset, "fused", "");
        for (label, extra) in [
            ("autograd", ""),
            ("autograd as before", "default pool spin"),
        ] {
            if let Some(x) = ratio(
                fused,
                find("training step", preset, "autograd", extra),
                "ms",
            ) {
                println!("training step ({preset}): fused {x:.2}x faster than {label}");
            }
        }
        let reach = format!("shadow reach {SHADOW_REACH}");
        let slots = format!("slot reach {SLOT_REACH}");
        for with in [&reach, &slots] {
            if let Some(x) = ratio(
                find("training step", preset, with, ""),
                find("training step", preset, "autograd", ""),
                "ms",
            ) {
                println!(
                    "training step ({preset}): fused with a {with} {x:.2}x faster than autograd"
                );
            }
        }
        // Amdahl's bound: the part of each fused step outside the decode kernel, timed inside
        // the same steps, caps what any faster decoder could give against the autograd path.
        let autograd_ms =
            find("training step", preset, "autograd", "").and_then(|r| r["ms"].as_f64());
        for r in results.iter().filter(|r| {
            let what = r["what"].as_str().unwrap_or("");
            what.starts_with("training step (fused") && r["preset"] == preset
        }) {
            if let (Some(rest), Some(ms), Some(autograd)) =
                (r["rest_ms"].as_f64(), r["ms"].as_f64(), autograd_ms)
            {
                let what = r["what"].as_str().unwrap_or("");
                let label = what
                    .split(';')
                    .next()
                    .unwrap_or("")
                    .trim_start_matches("training step (");
                println!(
                    "training step ({preset}, {label}): {rest:.1} of {ms:.1} ms outside the decode kernel; with a free decoder at most {:.2}x faster than autograd",
                    autograd / rest
                );
            }
        }
        for (label, extra) in [
            ("", ""),
            (" with a ", reach.as_str()),
            (" with a ", slots.as_str()),
        ] {
            let d = ratio(
                find("decoder", preset, "fused", extra),
                find("decoder", preset, "autograd", ""),
                "ms",
            );
            if let Some(x) = d {
                println!("decoder part of a step ({preset}): fused{label}{extra} {x:.2}x faster than autograd");
            }
        }
    }
    // The encoding rows of `kind` ("default encoding", "half-length refinement"; the bundled
    // model's, or "default encoding of PATH" for another's) through `path` ("fused",
    // "autograd", "fused; 1 thread)") at `size`².
    let encoding_rows = |kind: &str, path: &str, size: usize| {
        let prefix = format!("{kind} (");
        let path = path.to_string();
        results.iter().filter(move |r| {
            let what = r["what"].as_str().unwrap_or("");
            what.starts_with(&prefix) && what.contains(&path) && r["resolution"] == size
        })
    };
    for size in [64, 128] {
        let rows = |kind: &str, path: &str| encoding_rows(kind, path, size).next();
        let default = rows("default encoding", "fused");
        if let Some(x) = ratio(default, rows("default encoding", "autograd"), "cpu_s") {
            println!("default encoding at {size}²: fused {x:.2}x less CPU time than autograd");
        }
        if let Some(x) = ratio(rows("half-length refinement", "fused"), default, "cpu_s") {
            println!("half-length refinement at {size}²: {x:.2}x less CPU time than the default encoding");
        }
        if let Some(x) = ratio(default, rows("default encoding", "fused; 1 thread)"), "ms") {
            println!("default encoding at {size}²: two threads {x:.2}x faster than one");
        }
    }
    if let Some(model) = &other_model {
        // Both bundled rows at 128² on one thread (before and after the other model's), averaged.
        let one_thread = |kind: &str| -> Vec<f64> {
            encoding_rows(kind, "fused; 1 thread)", 128)
                .filter_map(|r| r["cpu_s"].as_f64())
                .collect()
        };
        let bundled = one_thread("default encoding");
        let other = one_thread(&format!("default encoding of {model}"));
        if let (false, Some(&cpu)) = (bundled.is_empty(), other.first()) {
            let mean = bundled.iter().sum::<f64>() / bundled.len() as f64;
            println!(
                "default encoding at 128², one thread: {model} takes {:.2}x the bundled model's CPU time",
                cpu / mean
            );
        }
    }
    if let Some(dir) = std::path::Path::new(&out).parent() {
        std::fs::create_dir_all(dir)?;
    }
    colf::io::write_atomic(
        std::path::Path::new(&out),
        serde_json::to_string_pretty(&results)?.as_bytes(),
    )?;
    eprintln!("bench: wrote {out}");
    Ok(())
}
