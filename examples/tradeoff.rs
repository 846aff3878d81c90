//! `make tradeoff`: the speed/accuracy curve of rendering shortcuts, on held-out scenes.
//!
//! For each of `--scenes` held-out synthetic scenes (`colf-synth --split test --size 128`),
//! view 0 is encoded in one pass (`colf-encode --fast --camera`, optionally `--prune P`) and views 1–3 are rendered:
//! - exactly (the reference: no pruning, full resolution, no `--adaptive`);
//! - adaptively with each ε of `--eps` (see `colf::render::adaptive`), after each `--prune`;
//! - exactly at half resolution, upsampled ×2 (bilinear) to compare at full resolution.
//!
//! Per configuration: the render time (median of `--reps` runs per frame, summed over frames)
//! and the speed-up over the exact render; PSNR against the exact render (8-bit, as the PNGs);
//! the PSNR loss against ground truth, mean PSNR(exact, GT) − mean PSNR(config, GT); and the
//! share of the foreground light-field evaluations of an exact render done (a slot on a pixel's
//! ray, and on its shadow line for a model that casts shadows along the light). Writes a
//! Markdown table (`--md`) and a plot (`--png`: speed-up against PSNR loss), and prints the
//! table and the figure of `--adaptive` at its default ε. The rayon thread count
//! (`RAYON_NUM_THREADS`) is stated with the times.
//!
//! Usage: `tradeoff --model M [--scenes 5] [--size 128] [--slots 7] [--eps 0,0.001,…]
//!         [--prune 0.003,0.01] [--reps 3] [--md docs/tradeoff.md] [--png docs/tradeoff.png]
//!         [--machine "the 2-core development machine"]`

use anyhow::{bail, Context, Result};
use colf::camera::{Cameras, Frame};
use colf::codes::Codes;
use colf::model::Colf;
use colf::render::{PreparedScene, RenderOptions};
use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

static FONT: &[u8] = include_bytes!("../assets/DejaVuSansMono.ttf");

struct Args {
    model: Option<String>,
    scenes: usize,
    size: u32,
    slots: usize,
    eps: Vec<f32>,
    prune: Vec<f64>,
    reps: usize,
    md: Option<PathBuf>,
    png: Option<PathBuf>,
    /// Where the times were taken, as the table says.
    machine: String,
}

fn parse_args() -> Result<Args> {
    let mut a = Args {
        model: None,
        scenes: 5,
        size: 128,
        slots: 7,
        eps: vec![0.0, 0.001, 0.003, 0.01, 0.03, 0.1],
        prune: vec![0.003, 0.01],
        reps: 3,
        md: None,
        png: None,
        machine: "the 2-core development machine".into(),
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let mut i = 0;
    while i < argv.len() {
        let val = argv
            .get(i + 1)
            .with_context(|| format!("{} needs a value", argv[i]))?;
        let list = |s: &str| -> Result<Vec<f64>> {
            s.split(',')
                .filter(|t| !t.is_empty())
                .map(|t| t.trim().parse::<f64>().map_err(Into::into))
                .collect()
        };
        match argv[i].as_str() {
            "--model" => a.model = Some(val.clone()),
            "--scenes" => a.scenes = val.parse()?,
            "--size" => a.size = val.parse()?,
            "--slots" => a.slots = val.parse()?,
            "--eps" => a.eps = list(val)?.into_iter().map(|v| v as f32).collect(),
            "--prune" => a.prune = list(val)?,
            "--reps" => a.reps = val.parse::<usize>()?.max(1),
            "--md" => a.md = Some(val.into()),
            "--png" => a.png = Some(val.into()),
            "--machine" => a.machine = val.clone(),
            other => bail!("unknown argument {other}"),
        }
        i += 2;
    }
    if a.size < 8 || !a.size.is_multiple_of(2) {
        bail!("--size must be even and at least 8");
    }
    Ok(a)
}

/// A binary of this build (target/release/NAME, beside examples/).
fn tool(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe()?;
    let p = exe
        .parent()
        .and_then(|p| p.parent())
        .map(|p| p.join(name))
        .context("locating the colf binaries")?;
    if !p.is_file() {
        bail!(
            "{} not found (run `cargo build --release` first)",
            p.display()
        );
    }
    Ok(p)
}

fn run(cmd: &mut Command) -> Result<()> {
    let out = cmd.output().with_context(|| format!("running {cmd:?}"))?;
    if !out.status.success() {
        bail!(
            "{cmd:?} failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(())
}

/// One configuration of the curve.
#[derive(Clone, Debug)]
struct Config {
    label: String,
    prune: f64,
    eps: Option<f32>,
    half_res: bool,
}

#[derive(Default, Clone, Debug)]
struct Tally {
    seconds: f64,
    sq_err_exact: f64,
    values: f64,
    psnr_gt: Vec<f64>,
    evaluated: usize,
    possible: usize,
}

fn quantize(v: &[f32]) -> Vec<f32> {
    v.iter()
        .map(|x| (x.clamp(0.0, 1.0) * 255.0).round() / 255.0)
        .collect()
}

/// Bilinear ×2 upsampling of an RGB image (align_corners = false, edges clamped).
fn upsample2(rgb: &[f32], w: usize, h: usize) -> Vec<f32> {
    let (w2, h2) = (2 * w, 2 * h);
    let mut out = vec![0f32; w2 * h2 * 3];
    let coord = |i: usize, n: usize| -> (usize, usize, f32) {
        let x = ((i as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, (n - 1) as f32);
        let x0 = x.floor() as usize;
        let x1 = (x0 + 1).min(n - 1);
        (x0, x1, x - x0 as f32)
    };
    for y in 0..h2 {
        let (y0, y1, fy) = coord(y, h);
        for x in 0..w2 {
            let (x0, x1, fx) = coord(x, w);
            for c in 0..3 {
                let p = |yy: usize, xx: usize| rgb[(yy * w + xx) * 3 + c];
                let top = p(y0, x0) * (1.0 - fx) + p(y0, x1) * fx;
                let bot = p(y1, x0) * (1.0 - fx) + p(y1, x1) * fx;
                out[(y * w2 + x) * 3 + c] = top * (1.0 - fy) + bot * fy;
            }
        }
    }
    out
}

fn half(frame: &Frame) -> Frame {
    let mut f = frame.clone();
    let i = &mut f.intrinsics;
    i.w /= 2;
    i.h /= 2;
    i.fl_x /= 2.0;
    i.fl_y /= 2.0;
    i.cx /= 2.0;
    i.cy /= 2.0;
    f
}

fn main() -> Result<()> {
    let args = parse_args()?;
    let model_path = colf::cli::model_path::resolve_model_path(args.model.as_deref())?;
    let model = Colf::load(&model_path)?;
    let identity = model.identity()?;
    let work = tempfile::tempdir()?;
    let data = work.path().join("data");
    eprintln!(
        "tradeoff: model {} (identity {identity}), {} held-out scenes at {}²",
        model_path.display(),
        args.scenes,
        args.size
    );
    run(Command::new(tool("colf-synth")?)
        .args(["--split", "test", "-q", "--seed", "0"])
        .args(["--scenes", &args.scenes.to_string()])
        .args(["--size", &args.size.to_string()])
        .arg("--out")
        .arg(&data))?;
    let mut configs = vec![Config {
        label: "exact".into(),
        prune: 0.0,
        eps: None,
        half_res: false,
    }];
    let mut prunes = vec![0.0];
    prunes.extend(args.prune.iter().copied());
    for &p in &prunes {
        if p > 0.0 {
            configs.push(Config {
                label: format!("prune {p}"),
                prune: p,
                eps: None,
                half_res: false,
            });
        }
        for &e in &args.eps {
            configs.push(Config {
                label: if p > 0.0 {
                    format!("prune {p} + adaptive {e}")
                } else {
                    format!("adaptive {e}")
                },
                prune: p,
                eps: Some(e),
                half_res: false,
            });
        }
    }
    configs.push(Config {
        label: "half resolution, upsampled".into(),
        prune: 0.0,
        eps: None,
        half_res: true,
    });
    let mut tallies = vec![Tally::default(); configs.len()];
    let mut slot_counts: Vec<(f64, usize)> = prunes.iter().map(|p| (*p, 0usize)).collect();
    for scene in 0..args.scenes {
        let dir = data.join(format!("scene_{scene:05}"));
        let cams_path = dir.join("transforms.json");
        let cameras = Cameras::read(cams_path.to_str().context("path")?)?;
        let mut prepared = Vec::new();
        for (pi, &p) in prunes.iter().enumerate() {
            let codes_path = work.path().join(format!("s{scene}_p{p}.codes"));
            let mut cmd = Command::new(tool("colf-encode")?);
            cmd.arg(dir.join("view_000.png"))
                .arg("--camera")
                .arg(&cams_path)
                .args(["--fast", "--slots", &args.slots.to_string()])
                .arg("--model")
                .arg(&model_path)
                .arg("-o")
                .arg(&codes_path);
            if p > 0.0 {
                cmd.args(["--prune", &p.to_string()]);
            }
            run(&mut cmd)?;
            let codes = Codes::read(codes_path.to_str().context("path")?)?;
            slot_counts[pi].1 += codes.slots.len();
            prepared.push((
                p,
                PreparedScene::new(&model, &codes, &codes_path.display().to_string())?,
            ));
        }
        for view in 1..cameras.frames.len() {
            let frame = &cameras.frames[view];
            let gt = colf::image_io::read_rgb(
                dir.join(format!("view_{view:03}.png"))
                    .to_str()
                    .context("path")?,
            )?;
            let mut exact: Option<Vec<f32>> = None;
            for (ci, cfg) in configs.iter().enumerate() {
                let scene_p = &prepared
                    .iter()
                    .find(|(p, _)| *p == cfg.prune)
                    .context("prune")?
                    .1;
                let opts = RenderOptions {
                    samples: None,
                    adaptive: cfg.eps,
                };
                let target = if cfg.half_res {
                    half(frame)
                } else {
                    frame.clone()
                };
                let mut times = Vec::new();
                let mut result = None;
                for _ in 0..args.reps {
                    let t = Instant::now();
                    let (r, stats) = scene_p.render_frame_with(&target, &opts)?;
                    times.push(t.elapsed().as_secs_f64());
                    result = Some((r, stats));
                }
                times.sort_by(|a, b| a.partial_cmp(b).unwrap());
                let (r, stats) = result.context("no render")?;
                let rgb = if cfg.half_res {
                    upsample2(&r.rgb, r.width as usize, r.height as usize)
                } else {
                    r.rgb
                };
                let rgb = quantize(&rgb);
                let t = &mut tallies[ci];
                t.seconds += times[times.len() / 2];
                t.psnr_gt.push(colf::metrics::psnr(&rgb, &gt.data)?);
                if let Some(s) = stats {
                    t.evaluated += s.evaluated;
                    t.possible += s.possible;
                }
                match &exact {
                    None => exact = Some(rgb),
                    Some(ex) => {
                        t.sq_err_exact += ex
                            .iter()
                            .zip(&rgb)
                            .map(|(a, b)| ((a - b) as f64).powi(2))
                            .sum::<f64>();
                        t.values += ex.len() as f64;
                    }
                }
            }
        }
        eprintln!("tradeoff: scene {}/{} done", scene + 1, args.scenes);
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let exact_t = tallies[0].seconds;
    let exact_gt = mean(&tallies[0].psnr_gt);
    let frames = tallies[0].psnr_gt.len();
    struct Row {
        label: String,
        prune: f64,
        eps: Option<f32>,
        half: bool,
        ms: f64,
        speedup: f64,
        psnr_exact: f64,
        loss: f64,
        evaluated: Option<f64>,
    }
    let rows: Vec<Row> = configs
        .iter()
        .zip(&tallies)
        .map(|(c, t)| {
            let mse = if t.values > 0.0 {
                t.sq_err_exact / t.values
            } else {
                0.0
            };
            Row {
                label: c.label.clone(),
                prune: c.prune,
                eps: c.eps,
                half: c.half_res,
                ms: 1e3 * t.seconds / frames.max(1) as f64,
                speedup: exact_t / t.seconds,
                psnr_exact: colf::metrics::psnr_from_mse(mse),
                loss: exact_gt - mean(&t.psnr_gt),
                evaluated: (t.possible > 0).then(|| t.evaluated as f64 / t.possible as f64),
            }
        })
        .collect();
    let best = rows
        .iter()
        .filter(|r| r.eps.is_some() && r.prune == 0.0 && r.loss <= 0.3)
        .max_by(|a, b| a.speedup.partial_cmp(&b.speedup).unwrap());
    let mut md = String::new();
    md.push_str(&format!(
        "Model `{}` (identity `{identity}`), {} held-out clevr567 scenes (`colf-synth --split test \
--seed 0 --size {}`), view 0 encoded in one pass with K = {} (`colf-encode --fast --camera`), views 1–3 rendered: \
{frames} frames. Exact render: {:.1} ms per frame, PSNR {:.2} dB against ground truth. Times are \
medians of {} run(s) per frame, summed over the frames, with {} rayon thread(s) on {}; every configuration renders each frame in turn, so the ratios of one table \
share its conditions (compare rows of one table, not tables). Mean slots kept: {}.\n\n",
        model_path.display(),
        args.scenes,
        args.size,
        args.slots,
        1e3 * exact_t / frames.max(1) as f64,
        exact_gt,
        args.reps,
        rayon::current_num_threads(),
        args.machine,
        slot_counts
            .iter()
            .map(|(p, n)| format!(
                "{} at prune {p}",
                *n as f64 / args.scenes.max(1) as f64
            ))
            .collect::<Vec<_>>()
            .join(", ")
    ));
    md.push_str("| configuration | ms / frame | speed-up | PSNR vs exact (dB) | PSNR loss vs GT (dB) | slot evaluations |\n");
    md.push_str("| --- | ---: | ---: | ---: | ---: | ---: |\n");
    for r in &rows {
        md.push_str(&format!(
            "| {} | {:.1} | {:.2}× | {} | {:+.3} | {} |\n",
            r.label,
            r.ms,
            r.speedup,
            if r.psnr_exact.is_finite() {
                format!("{:.1}", r.psnr_exact)
            } else {
                "identical".into()
            },
            r.loss,
            r.evaluated
                .map_or("".into(), |v| format!("{:.0} %", 100.0 * v))
        ));
    }
    let default_eps = colf::render::adaptive::RECOMMENDED_EPS;
    match rows
        .iter()
        .find(|r| r.prune == 0.0 && r.eps == Some(default_eps))
    {
        Some(d) => md.push_str(&format!(
            "\n**`--adaptive` at its default ε = {default_eps}: {:.2}× faster than the exact render, \
PSNR loss vs ground truth {:+.3} dB** ({:.1} ms against {:.1} ms a frame; {:.1} % of the \
foreground light-field evaluations).\n",
            d.speedup,
            d.loss,
            d.ms,
            1e3 * exact_t / frames.max(1) as f64,
            100.0 * d.evaluated.unwrap_or(0.0)
        )),
        None => md.push_str(&format!(
            "\n(The default ε = {default_eps} of `--adaptive` was not among `--eps`.)\n"
        )),
    }
    match best {
        Some(b) => md.push_str(&format!(
            "\nLargest speed-up of `--adaptive` alone with a PSNR loss ≤ 0.3 dB: ε = {} ({:.2}×, {:+.3} dB).\n",
            b.eps.unwrap_or(0.0),
            b.speedup,
            b.loss
        )),
        None => md.push_str("\nNo adaptive ε stayed within a PSNR loss of 0.3 dB.\n"),
    }
    print!("{md}");
    if let Some(p) = &args.md {
        colf::io::write_atomic(p, md.as_bytes())?;
        eprintln!("tradeoff: wrote {}", p.display());
    }
    if let Some(p) = &args.png {
        let points: Vec<(String, f64, f64, u8)> = rows
            .iter()
            .skip(1)
            .map(|r| {
                let series = if r.half {
                    2
                } else if r.prune > 0.0 {
                    1
                } else {
                    0
                };
                (
                    r.eps.map_or(r.label.clone(), |e| format!("{e}")),
                    r.speedup,
                    r.loss,
                    series,
                )
            })
            .collect();
        let png = plot(&points, &identity)?;
        colf::io::write_atomic(p, &png)?;
        eprintln!("tradeoff: wrote {}", p.display());
    }
    Ok(())
}

/// Speed-up (x) against PSNR loss (y), one colour per series.
fn plot(points: &[(String, f64, f64, u8)], identity: &str) -> Result<Vec<u8>> {
    use plotters::prelude::*;
    use plotters::style::FontStyle;
    plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
        .map_err(|_| anyhow::anyhow!("the bundled font is unreadable"))?;
    let (w, h) = (900u32, 560u32);
    let mut buffer = vec![255u8; (3 * w * h) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        root.fill(&WHITE)
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        let xmax = points.iter().map(|p| p.1).fold(1.0f64, f64::max) * 1.1;
        let ymin = points.iter().map(|p| p.2).fold(0.0f64, f64::min) - 0.05;
        let ymax = points.iter().map(|p| p.2).fold(0.3f64, f64::max) * 1.1 + 0.05;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                format!("colf render: speed-up vs PSNR loss (model {identity})"),
                ("sans-serif", 18),
            )
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(56)
            .build_cartesian_2d(0.0..xmax, ymin..ymax)
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        chart
            .configure_mesh()
            .x_desc("speed-up over the exact render (x)")
            .y_desc("PSNR loss vs ground truth (dB)")
            .draw()
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        let colors = [BLUE, RED, GREEN];
        let names = ["adaptive ε", "prune + adaptive ε", "half resolution"];
        for (series, (color, name)) in colors.iter().zip(names).enumerate() {
            let pts: Vec<(f64, f64)> = points
                .iter()
                .filter(|p| p.3 as usize == series)
                .map(|p| (p.1, p.2))
                .collect();
            if pts.is_empty() {
                continue;
            }
            let c = *color;
            chart
                .draw_series(pts.iter().map(|&(x, y)| Circle::new((x, y), 5, c.filled())))
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?
                .label(name)
                .legend(move |(x, y)| Circle::new((x, y), 5, c.filled()));
        }
        chart
            .draw_series(points.iter().map(|p| {
                Text::new(
                    p.0.clone(),
                    (p.1, p.2),
                    ("sans-serif", 12).into_font().color(&BLACK),
                )
            }))
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        chart
            .draw_series(LineSeries::new(
                vec![(0.0, 0.3), (xmax, 0.3)],
                BLACK.mix(0.4),
            ))
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?
            .label("0.3 dB")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK.mix(0.4)));
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        root.present().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
    }
    let img = image::RgbImage::from_raw(w, h, buffer).context("plot buffer")?;
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)?;
    Ok(out)
}
