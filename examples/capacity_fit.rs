//! Is it the decoder's design, or the latents it is given, that keeps a scene's renders soft?
//! `multiview_fit` bounds what any encoding can do: latents and frames fitted to all views.
//! This goes one step further and frees what the latents choose. For each scene:
//! 1. **latents**: view 0 encoded in one pass (with `--start encoded`: the first V views
//!    encoded together, the model's default multi-view encoding), then latents and frame
//!    origins refined on the first V views (`refine_slots`, `--latent-steps` steps), as
//!    `multiview_fit --views V`;
//! 2. **free hidden**: each slot's hypernetwork hidden activations (H of them) become free
//!    parameters instead of the latent that made them: the light field may be anything in the
//!    H-dimensional affine subspace the hypernetwork's heads span (the background as fitted);
//! 3. **free fields**: the light-field weights the hypernetworks generated from those latents
//!    become free parameters (one set per slot and the background), fitted by Adam on the
//!    same views for `--free-steps` steps; the shared heads and compositor stay the model's;
//! 4. **free fields + heads** (`--heads`): the same, and the model's shared colour, ordering
//!    and shadow heads and compositor fitted to this scene as well.
//!
//! With `--wide-latents N`, two more stages follow the free hidden one (and the free fields
//! are skipped), each `--free-steps` Adam steps at the latents' learning rate (`--latent-lr`):
//! - **latents, longer**: the fitted latents fitted on with this stage's optimiser (the
//!   reference for the next);
//! - **wider latents**: each slot's latent gets N more values, which reach every hidden layer's
//!   pre-activation through fixed random weights (drawn with the root-mean-square of the
//!   trained ones) beside the trained ones; the hypernetwork's RMS norm then spans all D + N
//!   values. A model trained with slots of D + N values would have learnt those weights, so
//!   this bounds from below what wider slots could draw with the same heads (issue 37: the
//!   paper's slots have 128 values, colf's 64).
//!
//! Each stage prints the mean PSNR of the fitted views (rendered whole, by the same decode).
//! If free fields reach far above the latents' bound, the light fields and the compositor can
//! draw the scene and the hypernetworks are what limit: their span (free hidden near the
//! latents: the heads' H directions) or the latent → hidden map (free hidden far above).
//!
//! Usage: `capacity_fit --data DIR [--model M] [--scenes 3] [--first 0] [--views 4] [--latent-steps 600]
//! [--free-steps 2000] [--rays 4096] [--lr 3e-4] [--hidden-lr 1e-2] [--heads] [--no-free-fields]
//! [--wide-latents N] [--latent-lr 1e-2] [--start one-pass|encoded]`
//! (`--lr` for free weights, `--hidden-lr` for free hidden activations: a hidden unit is
//! about as large as a latent, a weight two orders smaller).

use anyhow::{bail, Context, Result};
use candle_core::{Tensor, Var};
use colf::dataset::Dataset;
use colf::encode::refine::Pixels;
use colf::encode::InputView;
use colf::evaluate::fit_latents_to_views;
use colf::metrics::psnr;
use colf::model::hypernet::{GeneratedLayer, HyperNet};
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
    /// Extra latent values of the wider-latents stage (0: no such stage).
    wide_latents: usize,
    latent_lr: f64,
    /// The latents' fit starts from the first views' default encoding (`--start encoded`)
    /// instead of view 0's one pass.
    start_encoded: bool,
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
        wide_latents: 0,
        latent_lr: 1e-2,
        start_encoded: false,
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
            "--wide-latents" => a.wide_latents = val.parse().context("--wide-latents")?,
            "--latent-lr" => a.latent_lr = val.parse().context("--latent-lr")?,
            "--start" => {
                a.start_encoded = match val.as_str() {
                    "one-pass" => false,
                    "encoded" => true,
                    other => bail!("--start {other}: one-pass or encoded"),
                }
            }
            other => bail!("unknown option {other}"),
        }
    }
    if a.data.as_os_str().is_empty() || a.views == 0 || a.rays == 0 {
        bail!("usage: capacity_fit --data DIR [--model M] [--scenes N] [--views V] [--latent-steps S] [--free-steps S] [--rays R] [--lr LR] [--hidden-lr LR] [--heads] [--wide-latents N] [--latent-lr LR] [--start one-pass|encoded]");
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

/// The hidden activations of latents [K, D + N] through `layers`' weights, each widened by
/// fixed weights [H, N] for the N extra values (none: exactly the model's `hidden`), with the
/// hypernetwork's RMS norm over all D + N values when the model has it. Under the norm, N zero
/// values would scale the others up by √((D + N)/D), so the widened weights are scaled down by
/// as much: with the extra values at zero the hidden activations are the model's.
fn wide_hidden(
    hypernet: &HyperNet,
    latents: &Tensor,
    layers: &[(Tensor, Tensor)],
    extra: &[Tensor],
) -> Result<Tensor> {
    let rms_norm = hypernet.rms_norm();
    let x = hypernet.normalized(latents)?;
    let hidden = layers
        .iter()
        .enumerate()
        .map(|(l, (w, b))| {
            let w = match extra.get(l) {
                Some(e) => {
                    let (d, n) = (w.dim(1)?, e.dim(1)?);
                    let scale = if rms_norm {
                        (d as f64 / (d + n) as f64).sqrt()
                    } else {
                        1.0
                    };
                    (Tensor::cat(&[w, e], 1)? * scale)?
                }
                None => w.clone(),
            };
            Ok(x.matmul(&w.t()?)?.broadcast_add(b)?.relu()?)
        })
        .collect::<Result<Vec<Tensor>>>()?;
    Ok(Tensor::cat(&hidden, 1)?)
}

/// The two `--wide-latents` stages for one scene's fitted latents `fg` [1, K, D]: the latents
/// fitted on alone, then with `args.wide_latents` more values each; their PSNRs.
fn wide_latent_stages(
    model: &Colf,
    pixels: &Pixels,
    frames: &[DMat4],
    fg: &Tensor,
    bg_fields: &SlotWeights,
    scene: usize,
    args: &Args,
) -> Result<(f64, f64)> {
    let lf = model
        .model()
        .light_field()
        .context("not a light-field model")?;
    let hypernet = &lf.hypernet_fg;
    let (_, k, d) = fg.dims3()?;
    let fitted = fg.reshape((k, d))?.detach();
    let layers = hypernet.hidden_layer_weights();
    let mut rng = StdRng::seed_from_u64(2000 + scene as u64);
    // Fixed weights for the extra values, as large as the trained ones (root-mean-square).
    let extra = layers
        .iter()
        .map(|(w, _)| {
            let rms = w.sqr()?.mean_all()?.sqrt()?.to_scalar::<f32>()?;
            let a = rms * 3f32.sqrt();
            let h = w.dim(0)?;
            let values: Vec<f32> = (0..h * args.wide_latents)
                .map(|_| rng.random_range(-a..a))
                .collect();
            Ok(Tensor::from_vec(
                values,
                (h, args.wide_latents),
                model.device(),
            )?)
        })
        .collect::<Result<Vec<Tensor>>>()?;
    // Both stages must start from the model's own hidden activations (the weights as this
    // program applies them, and the widened ones at zero extra values), or they measure
    // something else.
    let own = hypernet.hidden(&fitted)?;
    let zeros = Tensor::zeros(
        (k, args.wide_latents),
        candle_core::DType::F32,
        model.device(),
    )?;
    let widened_start = Tensor::cat(&[&fitted, &zeros], 1)?;
    for (what, start) in [
        ("read", wide_hidden(hypernet, &fitted, &layers, &[])?),
        (
            "widened",
            wide_hidden(hypernet, &widened_start, &layers, &extra)?,
        ),
    ] {
        let gap = (start - &own)?.abs()?.max_all()?.to_scalar::<f32>()?;
        if gap > 1e-4 {
            bail!("the {what} hidden layers differ from the model's by {gap}");
        }
    }
    let mut scores = Vec::new();
    for wide in [false, true] {
        let z = Var::from_tensor(&fitted)?;
        let z_extra = Var::zeros(
            (k, args.wide_latents),
            candle_core::DType::F32,
            model.device(),
        )?;
        let fields = || -> Result<SlotWeights> {
            let (latents, extra): (Tensor, &[Tensor]) = if wide {
                (
                    Tensor::cat(&[z.as_tensor(), z_extra.as_tensor()], 1)?,
                    &extra,
                )
            } else {
                (z.as_tensor().clone(), &[])
            };
            let hidden = wide_hidden(hypernet, &latents, &layers, extra)?;
            let fg_fields = SlotWeights {
                layers: hypernet.from_hidden(&hidden)?,
            };
            Ok(SlotWeights::join_scenes(bg_fields, Some(&fg_fields), 1, k)?)
        };
        let mut vars = vec![("latents".to_string(), z.clone())];
        if wide {
            vars.push(("extra".to_string(), z_extra.clone()));
        }
        let stage = Stage {
            vars,
            lr: args.latent_lr,
            fields: &fields,
            seed: 3000 + scene as u64,
        };
        scores.push(fit(model, pixels, frames, stage, args)?);
    }
    Ok((scores[0], scores[1]))
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn main() -> Result<()> {
    let args = parse_args()?;
    let model = colf::cli::model_path::load_model(args.model.as_deref())?;
    let data = Dataset::open(&args.data)?;
    let (mut latents, mut free, mut heads) = (Vec::new(), Vec::new(), Vec::new());
    let (mut hidden, mut longer, mut wider) = (Vec::new(), Vec::new(), Vec::new());
    if args.wide_latents > 0 {
        println!(
            "| scene | latents fitted | free hidden | latents, longer | latents + {} values |",
            args.wide_latents
        );
    } else {
        println!("| scene | latents fitted | free hidden | free fields | free fields + heads |");
    }
    println!("| --- | ---: | ---: | ---: | ---: |");
    // `--start encoded`: colf-encode's default encoding of the fitted views, the same for every
    // scene.
    let start = args.start_encoded.then(|| {
        use clap::Parser;
        let flags = colf::cli::encode::EncodeArgs::try_parse_from(["colf-encode", "x.png"])
            .expect("colf-encode's defaults parse");
        flags
            .fit
            .encode_options_for_views(model.config(), None, 0, args.views)
    });
    for i in args.first..(args.first + args.scenes).min(data.len()) {
        let scene = data.load(i)?;
        let codes = fit_latents_to_views(
            &model,
            &scene,
            args.views,
            args.latent_steps,
            start.as_ref(),
        )?;
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
        if args.wide_latents > 0 {
            let (p_longer, p_wide) =
                wide_latent_stages(&model, &pixels, &frames, &fg, &bg_fields, i, &args)?;
            eprintln!(
                "{}: latents, longer {p_longer:.2} dB; + {} values {p_wide:.2} dB",
                scene.name, args.wide_latents
            );
            println!(
                "| {} | {p_latents:.2} | {p_hidden:.2} | {p_longer:.2} | {p_wide:.2} |",
                scene.name
            );
            latents.push(p_latents);
            longer.push(p_longer);
            wider.push(p_wide);
            continue;
        }
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
    if args.wide_latents > 0 {
        println!(
            "| mean | {:.2} | {:.2} | {:.2} | {:.2} |",
            mean(&latents),
            mean(&hidden),
            mean(&longer),
            mean(&wider)
        );
        return Ok(());
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
