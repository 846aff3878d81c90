//! How much of the novel-view error is the decoder, and how much is inferring a scene from one
//! image? For each held-out scene, view 0 is encoded as `colf-eval` does, then the latents and
//! frame origins are refined on the first V views (`colf::encode::refine::refine_slots`) and
//! every view is rendered. Printed per V, as the mean over scenes:
//! - `fitted`: PSNR of the views the latents were fitted to (how well the decoder can draw a
//!   scene whose latents are chosen for those views);
//! - `held out`: PSNR of the views from index max(V) on, the same views for every V (what more
//!   views of the scene buy for the views nobody saw); `—` when V covers every view.
//!
//! Usage: `multiview_fit --data DIR [--model M] [--scenes 10] [--views 1,2,3] [--steps 50]`
//! (refinement with the `colf-encode --refine` defaults otherwise).

use anyhow::{bail, Context, Result};
use colf::dataset::Dataset;
use colf::evaluate::fit_latents_to_views;
use colf::metrics::psnr;
use colf::render::PreparedScene;
use std::path::PathBuf;

struct Args {
    data: PathBuf,
    model: Option<String>,
    scenes: usize,
    views: Vec<usize>,
    steps: usize,
}

fn parse_args() -> Result<Args> {
    let mut a = Args {
        data: PathBuf::new(),
        model: None,
        scenes: 10,
        views: vec![1, 2, 3],
        steps: 50,
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    for pair in argv.chunks(2) {
        let [flag, val] = pair else {
            bail!("{} needs a value", pair[0]);
        };
        match flag.as_str() {
            "--data" => a.data = PathBuf::from(val),
            "--model" => a.model = Some(val.clone()),
            "--scenes" => a.scenes = val.parse().context("--scenes")?,
            "--steps" => a.steps = val.parse().context("--steps")?,
            "--views" => {
                a.views = val
                    .split(',')
                    .map(|v| v.trim().parse().context("--views"))
                    .collect::<Result<_>>()?
            }
            other => bail!("unknown option {other}"),
        }
    }
    if a.data.as_os_str().is_empty() {
        bail!(
            "usage: multiview_fit --data DIR [--model M] [--scenes N] [--views 1,2,3] [--steps S]"
        );
    }
    if a.views.contains(&0) {
        bail!("--views: fit to at least one view");
    }
    Ok(a)
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn main() -> Result<()> {
    let args = parse_args()?;
    let model = colf::cli::model_path::load_model(args.model.as_deref())?;
    let data = Dataset::open(&args.data)?;
    println!("| views fitted | fitted PSNR | held-out PSNR | scenes |");
    println!("| ---: | ---: | ---: | ---: |");
    let first_held_out = args.views.iter().copied().max().unwrap_or(1);
    for &fit in &args.views {
        let (mut fitted, mut held_out) = (Vec::new(), Vec::new());
        for i in 0..args.scenes.min(data.len()) {
            let scene = data.load(i)?;
            let codes = fit_latents_to_views(&model, &scene, fit, args.steps, None)?;
            let prepared = PreparedScene::new(&model, &codes, &scene.name)?;
            for (v, view) in scene.views.iter().enumerate() {
                let render = prepared.render_frame(&model, &view.frame)?;
                let p = psnr(&render.rgb, &view.image.data)?;
                if v < fit {
                    fitted.push(p);
                }
                if v >= first_held_out {
                    held_out.push(p);
                }
            }
            eprintln!("views fitted {fit}: scene {} done", scene.name);
        }
        // Fitting every view leaves none held out: say so rather than print a mean of nothing.
        let held_out = if held_out.is_empty() {
            "—".to_string()
        } else {
            format!("{:.2} dB", mean(&held_out))
        };
        println!(
            "| {fit} | {:.2} dB | {held_out} | {} |",
            mean(&fitted),
            args.scenes.min(data.len())
        );
    }
    Ok(())
}
