//! Timings and memory of the model (ignored by default; run with
//! `cargo test --release --test model_bench -- --ignored --nocapture --test-threads 1`).
//! `render_60_slots_paper` alone under `/usr/bin/time -v` gives the peak memory of a 128²
//! frame with 60 foreground slots.

use colf::model::{Colf, Config};
use glam::{DMat4, DVec3};
use std::time::Instant;

fn frame_rays(n: usize) -> (Vec<DVec3>, Vec<DVec3>) {
    // A clevr567-like camera: distance 12.4, elevation 40°, looking at the origin.
    let eye = DVec3::new(
        0.0,
        -12.4 * 40f64.to_radians().cos(),
        12.4 * 40f64.to_radians().sin(),
    );
    let forward = (-eye).normalize();
    let right = forward.cross(DVec3::Z).normalize();
    let up = right.cross(forward);
    let f = 1.09375;
    let mut o = Vec::with_capacity(n * n);
    let mut d = Vec::with_capacity(n * n);
    for j in 0..n {
        for i in 0..n {
            let u = ((i as f64 + 0.5) / n as f64 - 0.5) / f;
            let v = ((j as f64 + 0.5) / n as f64 - 0.5) / f;
            o.push(eye);
            d.push(forward + u * right - v * up);
        }
    }
    (o, d)
}

fn image(n: usize) -> Vec<f32> {
    (0..n * n * 3)
        .map(|i| ((i * 7919) % 255) as f32 / 255.0)
        .collect()
}

fn render(colf: &Colf, k: usize, size: usize) -> (f64, f64) {
    let enc = colf.encode(&image(64), 64, 64, k.min(1), 0).unwrap();
    let fg: Vec<Vec<f32>> = (0..k)
        .map(|i| {
            enc.fg_latents[0]
                .iter()
                .map(|v| v + 0.01 * i as f32)
                .collect()
        })
        .collect();
    let frames: Vec<DMat4> = (0..k)
        .map(|i| {
            DMat4::from_translation(DVec3::new((i % 8) as f64 - 4.0, (i / 8) as f64 - 4.0, 0.0))
        })
        .collect();
    let (o, d) = frame_rays(size);
    let t = Instant::now();
    let prepared = colf.prepare(&fg, &enc.bg_latent).unwrap();
    let prep = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let out = colf.render_rays(&prepared, &frames, &o, &d).unwrap();
    let ren = t.elapsed().as_secs_f64();
    assert!(out.rgb.iter().all(|v| v.is_finite()));
    (prep, ren)
}

#[test]
#[ignore]
fn bench_presets() {
    for cfg in [Config::small(), Config::paper()] {
        let t = Instant::now();
        let colf = Colf::init(&cfg, 0).unwrap();
        let init = t.elapsed().as_secs_f64();
        let bytes = colf.to_bytes().unwrap().0.len();
        println!(
            "{}: {} parameters, file {} bytes ({:.1} MiB), init {:.2} s",
            cfg.preset,
            colf.num_parameters(),
            bytes,
            bytes as f64 / 1048576.0,
            init
        );
        let img = image(128);
        colf.encode(&img, 128, 128, 7, 0).unwrap(); // warm-up
        let mut times = Vec::new();
        for seed in 0..3 {
            let t = Instant::now();
            colf.encode(&img, 128, 128, 7, seed).unwrap();
            times.push(t.elapsed().as_secs_f64());
        }
        println!(
            "  encode 128² image, K=7: {:?} s",
            times.iter().map(|t| format!("{t:.3}")).collect::<Vec<_>>()
        );
        for k in [2, 7, 60] {
            render(&colf, k, 32); // warm-up
            let (prep, ren) = render(&colf, k, 128);
            println!("  K={k}: prepare {prep:.3} s, render 128² (16384 rays) {ren:.3} s");
        }
    }
}

#[test]
#[ignore]
fn render_60_slots_paper() {
    let colf = Colf::init(&Config::paper(), 0).unwrap();
    let (prep, ren) = render(&colf, 60, 128);
    println!("paper K=60: prepare {prep:.3} s, render 128² {ren:.3} s");
}

#[test]
#[ignore]
fn render_60_slots_small() {
    let colf = Colf::init(&Config::small(), 0).unwrap();
    let (prep, ren) = render(&colf, 60, 128);
    println!("small K=60: prepare {prep:.3} s, render 128² {ren:.3} s");
}

#[test]
#[ignore]
fn profile_decode_parts() {
    use colf::model::{RayBatch, SceneRays};
    for cfg in [Config::small(), Config::paper()] {
        let colf = Colf::init(&cfg, 0).unwrap();
        let k = 7;
        let enc = colf.encode(&image(64), 64, 64, k, 0).unwrap();
        let prepared_t = {
            let fg = candle_core::Tensor::from_vec(
                enc.fg_latents.concat(),
                (1, k, cfg.slot_dim),
                colf.device(),
            )
            .unwrap();
            let bg = candle_core::Tensor::from_vec(
                enc.bg_latent.clone(),
                (1, cfg.slot_dim),
                colf.device(),
            )
            .unwrap();
            colf.model().prepare(&fg, &bg).unwrap()
        };
        let frames = vec![DMat4::IDENTITY; k];
        let (o, d) = frame_rays(128);
        for _ in 0..2 {
            let t = Instant::now();
            let rays = RayBatch::new(
                &cfg,
                &[SceneRays {
                    slot_to_world: &frames,
                    origins: &o,
                    dirs: &d,
                }],
                colf.device(),
            )
            .unwrap();
            let t_rays = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let feat = prepared_t.forward(&rays.coords).unwrap();
            let t_lfn = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let (c, ord) = colf.model().heads.forward(&feat).unwrap();
            let t_heads = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let dec = colf.model().decode(&prepared_t, &rays).unwrap();
            let _ = dec.rgb.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let t_all = t.elapsed().as_secs_f64();
            drop((c, ord));
            println!("{} K={k}: rays {t_rays:.3} lfn {t_lfn:.3} heads {t_heads:.3} decode total {t_all:.3}", cfg.preset);
        }
    }
}

/// Forward + backward of a TRAINING-NOTES-sized step: 4 scenes, K = 7, 1024 rays per scene.
#[test]
#[ignore]
fn train_step_small() {
    use candle_core::{Device, Tensor};
    use colf::model::{RayBatch, SceneRays};
    use rand::SeedableRng;
    let cfg = Config::small();
    let colf = Colf::init(&cfg, 0).unwrap().into_trainable().unwrap();
    let s = cfg.encoder_size;
    let dev = Device::Cpu;
    let imgs: Vec<f32> = (0..4).flat_map(|_| image(s)).collect();
    let images = Tensor::from_vec(imgs, (4, s, s, 3), &dev)
        .unwrap()
        .permute((0, 3, 1, 2))
        .unwrap()
        .contiguous()
        .unwrap();
    let (o, d) = frame_rays(32);
    let frames = vec![DMat4::IDENTITY; 7];
    let scenes: Vec<SceneRays> = (0..4)
        .map(|_| SceneRays {
            slot_to_world: &frames,
            origins: &o,
            dirs: &d,
        })
        .collect();
    let mut rng = rand::rngs::StdRng::seed_from_u64(0);
    for step in 0..4 {
        let t = Instant::now();
        let model = colf.model();
        let slots = model.encode(&images, 7, &mut rng).unwrap();
        // Odd steps detach the slots: the difference is the encoder's share of the backward.
        let (fg, bg) = if step % 2 == 1 {
            (slots.fg.detach(), slots.bg.detach())
        } else {
            (slots.fg.clone(), slots.bg.clone())
        };
        let fields = model.prepare(&fg, &bg).unwrap();
        let rays = RayBatch::new(&cfg, &scenes, &dev).unwrap();
        let out = model.decode(&fields, &rays).unwrap();
        let loss = out.rgb.sqr().unwrap().mean_all().unwrap();
        let t_fwd = t.elapsed().as_secs_f64();
        let _grads = loss.backward().unwrap();
        println!(
            "step {step} ({}): forward {t_fwd:.3} s, forward+backward {:.3} s",
            if step % 2 == 1 {
                "decoder only"
            } else {
                "full"
            },
            t.elapsed().as_secs_f64()
        );
    }
}

/// Where the decoder's backward time goes (4 scenes, K = 7, 1024 rays each).
#[test]
#[ignore]
fn profile_decoder_backward() {
    use candle_core::{Device, Tensor};
    use colf::model::{RayBatch, SceneRays};
    let cfg = Config::small();
    let colf = Colf::init(&cfg, 0).unwrap().into_trainable().unwrap();
    let dev = Device::Cpu;
    let model = colf.model();
    let fg = Tensor::ones((4, 7, cfg.slot_dim), candle_core::DType::F32, &dev).unwrap();
    let bg = Tensor::ones((4, cfg.slot_dim), candle_core::DType::F32, &dev).unwrap();
    let (o, d) = frame_rays(32);
    let frames = vec![DMat4::IDENTITY; 7];
    let scenes: Vec<SceneRays> = (0..4)
        .map(|_| SceneRays {
            slot_to_world: &frames,
            origins: &o,
            dirs: &d,
        })
        .collect();
    let rays = RayBatch::new(&cfg, &scenes, &dev).unwrap();
    for _ in 0..2 {
        let t = Instant::now();
        let fields = model.prepare(&fg, &bg).unwrap();
        let feat = fields.forward(&rays.coords).unwrap();
        feat.sqr().unwrap().mean_all().unwrap().backward().unwrap();
        let t_lfn = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let fields = model.prepare(&fg, &bg).unwrap();
        let feat = fields.forward(&rays.coords).unwrap();
        let (c, ord) = model.heads.forward(&feat).unwrap();
        (c.sum_all().unwrap() + ord.sum_all().unwrap())
            .unwrap()
            .backward()
            .unwrap();
        let t_heads = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let fields = model.prepare(&fg, &bg).unwrap();
        let out = model.decode(&fields, &rays).unwrap();
        out.rgb
            .sqr()
            .unwrap()
            .mean_all()
            .unwrap()
            .backward()
            .unwrap();
        let t_all = t.elapsed().as_secs_f64();
        println!(
            "fwd+bwd: hypernet+lfn {t_lfn:.3} s, +heads {t_heads:.3} s, full decode {t_all:.3} s"
        );
    }
}
