//! Is it the decoder's design, or the latents it is given, that keeps a scene's renders soft?
//! `multiview_fit` bounds what any encoding can do: latents and frames fitted to all views.
//! This goes one step further and frees what the latents choose. For each scene:
//! 1. **latents**: view 0 encoded in one pass, then latents and frame origins refined on the
//!    first V views (`refine_slots`, `--latent-steps` steps), as `multiview_fit --views V`;
//! 2. **free hidden**: each slot's hypernetwork hidden activations (H of them) become free
//!    parameters instead of the latent that made them: the light field may be anything in the
//!    H-dimensional affine subspace the hypernetwork's heads span (the background as fitted);
//! 3. **free fields**: the light-field weights the hypernetworks generated from those latents
//!    become free parameters (one set per slot and the background), fitted by Adam on the
//!    same views for `--free-steps` steps; the shared heads and compositor stay the model's;
//! 4. **free fields + heads** (`--heads`): the same, and the model's shared colour, ordering
//!    and shadow heads and compositor fitted to this scene as well.
//!
//! Each stage prints the mean PSNR of the fitted views (rendered whole, by the same decode).
//! If free fields reach far above the latents' bound, the light fields and the compositor can
//! draw the scene and the hypernetworks are what limit: their span (free hidden near the
//! latents: the heads' H directions) or the latent → hidden map (free hidden far above).
//!
//! Usage: `capacity_fit --data DIR [--model M] [--scenes 3] [--first 0] [--views 4] [--latent-steps 600]
//! [--free-steps 2000] [--rays 4096] [--lr 3e-4] [--hidden-lr 1e-2] [--heads] [--no-free-fields]`
//! (`--lr` for free weights, `--hidden-lr` for free hidden activations: a hidden unit is
//! about as large as a latent, a weight two orders smaller).

use anyhow::{bail, Context, Result};
use candle_core::{Tensor, Var};
use colf::dataset::Dataset;
use colf::encode::refine::Pixels;
use colf::encode::InputView;
use colf::evaluate::fit_latents_to_views;
use colf::metrics::psnr;
use colf::model::hypernet::GeneratedLayer;
use colf::model::{Colf, SlotWeights};
use colf::optim::{Adam, AdamConfig};
use glam::DMat4;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use std::path::PathBuf;

struct Args {
    data: PathBuf,
    model: Option<String>,
    scenes: usize,
    /// Index of the first scene (`--first`).
    first: usize,
    views: usize,
    latent_steps: usize,
    free_steps: usize,
    rays: usize,
    lr: f64,
    hidden_lr: f64,
    heads: bool,
    /// Stop after the free hidden stage (`--no-free-fields`).
    no_free_fields: bool,
}

fn parse_args() -> Result<Args> {
    let mut a = Args {
        data: PathBuf::new(),
        model: None,
        scenes: 3,
        first: 0,
        views: 4,
        latent_steps: 600,
        free_steps: 2000,
        rays: 4096,
        lr: 3e-4,
        hidden_lr: 1e-2,
        heads: false,
        no_free_fields: false,
    };
    let mut argv = std::env::args().skip(1);
    while let Some(flag) = argv.next() {
        if flag == "--heads" {
            a.heads = true;
            continue;
        }
        if flag == "--no-free-fields" {
            a.no_free_fields = true;
            continue;
        }
        let val = argv
            .next()
            .with_context(|| format!("{flag} needs a value"))?;
        match flag.as_str() {
            "--data" => a.data = PathBuf::from(val),
            "--model" => a.model = Some(val),
            "--scenes" => a.scenes = val.parse().context("--scenes")?,
            "--first" => a.first = val.parse().context("--first")?,
            "--views" => a.views = val.parse().context("--views")?,
            "--latent-steps" => a.latent_steps = val.parse().context("--latent-steps")?,
            "--free-steps" => a.free_steps = val.parse().context("--free-steps")?,
            "--rays" => a.rays = val.parse().context("--rays")?,
            "--lr" => a.lr = val.parse().context("--lr")?,
            "--hidden-lr" => a.hidden_lr = val.parse().context("--hidden-lr")?,
            other => bail!("unknown option {other}"),
        }
    }
    if a.data.as_os_str().is_empty() || a.views == 0 || a.rays == 0 {
        bail!("usage: capacity_fit --data DIR [--model M] [--scenes N] [--views V] [--latent-steps S] [--free-steps S] [--rays R] [--lr LR] [--hidden-lr LR] [--heads]");
    }
    Ok(a)
}

/// Mean PSNR over the views of `pixels`, each rendered whole by `fields`.
fn views_psnr(
    model: &Colf,
    pixels: &Pixels,
    fields: &SlotWeights,
    frames: &[DMat4],
) -> Result<f64> {
    let mut total = 0.0;
    for &(first, w, h) in &pixels.views {
        let n = w * h;
        let mut rgb = Vec::with_capacity(3 * n);
        for start in (first..first + n).step_by(4096) {
            let pick: Vec<usize> = (start..(start + 4096).min(first + n)).collect();
            let (rays, _) = pixels.batch(model, frames, Some(&pick))?;
            let out = model.model().decode(fields, &rays)?;
            rgb.extend(out.rgb.flatten_all()?.to_vec1::<f32>()?);
        }
        total += psnr(&rgb, &pixels.rgb[3 * first..3 * (first + n)])?;
    }
    Ok(total / pixels.views.len() as f64)
}

/// The prepared light fields as free parameters: each layer's weight and bias a `Var`.
fn free_fields(fields: &SlotWeights) -> Result<(SlotWeights, Vec<(String, Var)>)> {
    let mut vars = Vec::new();
    let mut layers = Vec::new();
    for (i, l) in fields.layers.iter().enumerate() {
        let w = Var::from_tensor(&l.weight.detach())?;
        let b = Var::from_tensor(&l.bias.detach())?;
        layers.push(GeneratedLayer {
            weight: w.as_tensor().clone(),
            bias: b.as_tensor().clone(),
        });
        vars.push((format!("field.{i}.weight"), w));
        vars.push((format!("field.{i}.bias"), b));
    }
    Ok((SlotWeights { layers }, vars))
}

/// What one stage fits: the variables, their learning rate, and how the light fields are
/// made from them (evaluated anew each step: free hidden activations pass through the heads).
struct Stage<'a> {
    vars: Vec<(String, Var)>,
    lr: f64,
    fields: &'a dyn Fn() -> Result<SlotWeights>,
    seed: u64,
}

/// `--free-steps` Adam steps of `--rays` random pixels on the colour MSE, the learning rate
/// decayed by a half cosine to a tenth; the mean PSNR of the views rendered whole at the end.
fn fit(model: &Colf, pixels: &Pixels, frames: &[DMat4], stage: Stage, args: &Args) -> Result<f64> {
    let mut adam = Adam::new(
        stage.vars,
        AdamConfig {
            clip_norm: None,
            ..AdamConfig::default()
        },
    )?;
    let mut rng = StdRng::seed_from_u64(stage.seed);
    let n = pixels.origins.len();
    for step in 0..args.free_steps {
        let pick: Vec<usize> = (0..args.rays).map(|_| rng.random_range(0..n)).collect();
        let (rays, target) = pixels.batch(model, frames, Some(&pick))?;
        let out = model.model().decode(&(stage.fields)()?, &rays)?;
        let loss = (&out.rgb - &target)?.sqr()?.mean_all()?;
        let grads = loss.backward()?;
        let t = step as f64 / args.free_steps.max(1) as f64;
        let lr = stage.lr * (0.1 + 0.9 * 0.5 * (1.0 + (std::f64::consts::PI * t).cos()));
        let stats = adam.step(&grads, lr)?;
        if step % 250 == 0 {
            let mse = loss.to_scalar::<f32>()? as f64;
            eprintln!(
                "  step {step}: sampled-ray PSNR {:.2}, gradient norm {:.3e}, {} without a gradient",
                -10.0 * mse.log10(),
                stats.grad_norm,
                stats.missing_grads
            );
        }
    }
    views_psnr(model, pixels, &(stage.fields)()?, frames)
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn main() -> Result<()> {
    let args = parse_args()?;
    let model = colf::cli::model_path::load_model(args.model.as_deref())?;
    let data = Dataset::open(&args.data)?;
    let (mut latents, mut free, mut heads) = (Vec::new(), Vec::new(), Vec::new());
    let mut hidden = Vec::new();
    println!("| scene | latents fitted | free hidden | free fields | free fields + heads |");
    println!("| --- | ---: | ---: | ---: | ---: |");
    for i in args.first..(args.first + args.scenes).min(data.len()) {
        let scene = data.load(i)?;
        let codes = fit_latents_to_views(&model, &scene, args.views, args.latent_steps)?;
        let views: Vec<InputView> = scene.views[..args.views]
            .iter()
            .map(|v| InputView::new(&v.frame, &v.image))
            .collect();
        let pixels = Pixels::gather(&views.iter().collect::<Vec<_>>());
        let frames: Vec<DMat4> = codes.slots.iter().map(|s| s.slot_to_world).collect();
        let dev = model.device();
        let (k, d) = (codes.slots.len(), codes.dim());
        let fg = Tensor::from_vec(
            codes
                .slots
                .iter()
                .flat_map(|s| s.latent.clone())
                .collect::<Vec<f32>>(),
            (1, k, d),
            dev,
        )?;
        let bg = Tensor::from_vec(codes.background.clone(), (1, d), dev)?;
        let prepared = model.model().prepare(&fg, &bg)?;
        let p_latents = views_psnr(&model, &pixels, &prepared, &frames)?;
        eprintln!("{}: latents fitted {p_latents:.2} dB", scene.name);
        let lf = model
            .model()
            .light_field()
            .context("not a light-field model")?;
        let h = Var::from_tensor(&lf.hypernet_fg.hidden(&fg.reshape((k, d))?)?.detach())?;
        let bg_fields = SlotWeights {
            layers: lf
                .background
                .forward(&bg)?
                .into_iter()
                .map(|l| GeneratedLayer {
                    weight: l.weight.detach(),
                    bias: l.bias.detach(),
                })
                .collect(),
        };
        let spanned = || -> Result<SlotWeights> {
            let fg_fields = SlotWeights {
                layers: lf.hypernet_fg.from_hidden(h.as_tensor())?,
            };
            Ok(SlotWeights::join_scenes(
                &bg_fields,
                Some(&fg_fields),
                1,
                k,
            )?)
        };
        let stage = Stage {
            vars: vec![("hidden".to_string(), h.clone())],
            lr: args.hidden_lr,
            fields: &spanned,
            seed: 500 + i as u64,
        };
        let p_hidden = fit(&model, &pixels, &frames, stage, &args)?;
        eprintln!("{}: free hidden {p_hidden:.2} dB", scene.name);
        hidden.push(p_hidden);
        if args.no_free_fields {
            println!(
                "| {} | {p_latents:.2} | {p_hidden:.2} | — | — |",
                scene.name
            );
            latents.push(p_latents);
            continue;
        }
        let (fields, vars) = free_fields(&prepared)?;
        let same_fields = || -> Result<SlotWeights> { Ok(fields.clone()) };
        let stage = Stage {
            vars: vars.clone(),
            lr: args.lr,
            fields: &same_fields,
            seed: i as u64,
        };
        let p_free = fit(&model, &pixels, &frames, stage, &args)?;
        eprintln!("{}: free fields {p_free:.2} dB", scene.name);
        let p_heads = if args.heads {
            // A trainable copy of the model for this scene alone, and the shared modules a
            // decode reads besides the generated weights (heads, compositor) freed too.
            let scene_model =
                colf::cli::model_path::load_model(args.model.as_deref())?.into_trainable()?;
            let mut all = vars;
            all.extend(
                scene_model
                    .named_vars()
                    .into_iter()
                    .filter(|(n, _)| n.starts_with("heads") || n.starts_with("compositor")),
            );
            let stage = Stage {
                vars: all,
                lr: args.lr,
                fields: &same_fields,
                seed: 1000 + i as u64,
            };
            let p = fit(&scene_model, &pixels, &frames, stage, &args)?;
            eprintln!("{}: free fields + heads {p:.2} dB", scene.name);
            heads.push(p);
            format!("{p:.2}")
        } else {
            "—".into()
        };
        println!(
            "| {} | {p_latents:.2} | {p_hidden:.2} | {p_free:.2} | {p_heads} |",
            scene.name
        );
        latents.push(p_latents);
        free.push(p_free);
    }
    let heads = if heads.is_empty() {
        "—".into()
    } else {
        format!("{:.2}", mean(&heads))
    };
    let free = if free.is_empty() {
        "—".into()
    } else {
        format!("{:.2}", mean(&free))
    };
    println!(
        "| mean | {:.2} | {:.2} | {free} | {heads} |",
        mean(&latents),
        mean(&hidden),
    );
    Ok(())
}
