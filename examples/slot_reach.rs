//! How far from its frame origin does a foreground slot draw — what would `slot_reach = ρ`
//! (docs/model.md) change for a model trained without it? For held-out scenes: view 0 encoded
//! in one pass, every view rendered by the fast renderer exactly and then with each foreground
//! slot left out of the rays that pass farther than ρ from its frame origin (no colour, weight
//! or shadow there, as the config does). Prints, per ρ, the share of the foreground evaluations
//! kept and the PSNR of the bounded render against the exact one and against the ground truth;
//! then the exact render's compositor weights binned by the ray's distance from the slot.
//!
//! `slot_reach --data DIR [--model M] [--scenes N] [--reach 2,2.5,3]` (docs/speed.md)

use anyhow::{Context, Result};
use colf::dataset::Dataset;
use colf::encode::EncodeOptions;
use colf::evaluate::encode_scene;
use colf::render::fast::{Active, FastRenderer};
use glam::DVec3;
use std::path::PathBuf;

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let (mut data, mut model_path, mut scenes) = (None, None, 8usize);
    let mut reaches = vec![1.0, 1.5, 2.0, 2.5, 3.0, 4.0];
    while let Some(a) = args.next() {
        let mut value = || args.next().context("missing value");
        match a.as_str() {
            "--data" => data = Some(PathBuf::from(value()?)),
            "--model" => model_path = Some(value()?),
            "--scenes" => scenes = value()?.parse()?,
            "--reach" => {
                reaches = value()?
                    .split(',')
                    .map(|s| s.parse())
                    .collect::<Result<_, _>>()?
            }
            _ => anyhow::bail!(
                "unknown argument {a} (usage: slot_reach --data DIR [--model M] [--scenes N] [--reach 2,2.5,3])"
            ),
        }
    }
    let model = colf::cli::model_path::load_model(model_path.as_deref())?;
    let data = Dataset::open(&data.context("--data DIR")?)?;
    let opts = EncodeOptions::one_pass(model.config().default_slots);
    // Per reach: kept evaluations, possible ones, squared errors against exact and truth.
    let mut kept = vec![0usize; reaches.len()];
    let mut possible = 0usize;
    let (mut vs_exact, mut vs_truth) = (vec![0f64; reaches.len()], vec![0f64; reaches.len()]);
    let mut exact_truth = 0f64;
    let mut values = 0usize;
    // Weight bins by distance: edges in frame units.
    let edges = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, f64::INFINITY];
    let mut bins = vec![(0usize, 0f32, 0f64); edges.len()];
    for i in 0..scenes.min(data.len()) {
        let scene = data.load(i)?;
        let codes = encode_scene(&model, &scene, &[0], &opts)?;
        let latents: Vec<Vec<f32>> = codes.slots.iter().map(|s| s.latent.clone()).collect();
        let frames: Vec<_> = codes.slots.iter().map(|s| s.slot_to_world).collect();
        let prepared = model.prepare(&latents, &codes.background)?;
        let renderer = FastRenderer::new(&model, &prepared, &frames)?;
        let inverses = colf::model::rays::world_to_slot(&frames)?;
        let s = 1 + frames.len();
        for view in &scene.views {
            let rays = view.frame.rays();
            let origins: Vec<DVec3> = rays.iter().map(|r| r.origin).collect();
            let dirs: Vec<DVec3> = rays.iter().map(|r| r.direction).collect();
            let exact = renderer.render(&origins, &dirs, None, None)?;
            // Each ray's distance from each foreground frame origin, in frame units.
            let mut dist = vec![0f64; origins.len() * s];
            for (r, (o, d)) in origins.iter().zip(&dirs).enumerate() {
                for (k, inv) in inverses.iter().enumerate() {
                    let o = inv.transform_point3(*o);
                    let d = inv.transform_vector3(*d).normalize();
                    dist[r * s + 1 + k] = (o - o.dot(d) * d).length();
                }
            }
            for (r, w) in exact.weights.chunks_exact(s).enumerate() {
                for k in 1..s {
                    let rho = dist[r * s + k];
                    let b = edges.iter().position(|&e| rho <= e).unwrap();
                    bins[b].0 += 1;
                    bins[b].1 = bins[b].1.max(w[k]);
                    bins[b].2 += w[k] as f64;
                }
            }
            let truth = &view.image.data;
            let n = truth.len() as f64;
            exact_truth += mse(&exact.rgb, truth) * n;
            values += truth.len();
            possible += origins.len() * (s - 1);
            for (j, &reach) in reaches.iter().enumerate() {
                let fields: Vec<bool> = (0..origins.len() * s)
                    .map(|u| u % s == 0 || dist[u] <= reach)
                    .collect();
                kept[j] += fields
                    .iter()
                    .enumerate()
                    .filter(|(u, &f)| f && u % s != 0)
                    .count();
                // Shadows where the slot is (`shadows: None`), as `slot_reach` has them.
                let active = Active {
                    fields: &fields,
                    shadows: None,
                };
                let bounded = renderer.render_active(&origins, &dirs, active)?;
                vs_exact[j] += mse(&bounded.rgb, &exact.rgb) * n;
                vs_truth[j] += mse(&bounded.rgb, truth) * n;
            }
        }
        eprintln!("{}: {} slots", scene.name, s - 1);
    }
    let db = |m: f64| colf::metrics::psnr_from_mse(m / values as f64);
    println!("exact render against the truth: {:.3} dB", db(exact_truth));
    println!("| reach | evaluations kept | PSNR against exact | PSNR against truth |");
    println!("| ---: | ---: | ---: | ---: |");
    for (j, reach) in reaches.iter().enumerate() {
        println!(
            "| {reach} | {:.1} % | {:.2} | {:.3} |",
            100.0 * kept[j] as f64 / possible as f64,
            db(vs_exact[j]),
            db(vs_truth[j])
        );
    }
    println!("\n| ray within | (ray, slot) pairs | max weight | mean weight |");
    println!("| ---: | ---: | ---: | ---: |");
    for (e, (count, max, sum)) in edges.iter().zip(&bins) {
        println!(
            "| {e} | {count} | {max:.4} | {:.6} |",
            sum / (*count).max(1) as f64
        );
    }
    Ok(())
}

fn mse(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / a.len() as f64
}
