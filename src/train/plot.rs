//! A picture of training: loss and PSNR curves drawn from the JSON-lines log (`colf-train plot`).
//!
//! Four panels share the step axis: loss (log scale), PSNR of the sampled rays and of the rays
//! on objects, the foreground share of object rays with FG-ARI, and evaluations (novel-view
//! PSNR on the held-out scenes) where the log has them. Noisy per-step values are drawn faint
//! with a moving average on top. Several logs share one picture: each run is drawn in its own
//! colour in every panel.

use anyhow::{anyhow, bail, Context, Result};
use plotters::coord::types::RangedCoordf64;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

/// The font is bundled (DejaVu Sans Mono, `assets/`), so plots need no system fonts.
static FONT: &[u8] = include_bytes!("../../assets/DejaVuSansMono.ttf");

/// Series read from a log.
#[derive(Default, Debug)]
pub struct Curves {
    pub step: Vec<f64>,
    pub loss: Vec<f64>,
    pub psnr: Vec<f64>,
    pub obj_psnr: Vec<f64>,
    pub fg_share: Vec<f64>,
    pub fg_ari: Vec<f64>,
    /// (step, novel-view PSNR, FG-ARI) of evaluations.
    pub eval: Vec<(f64, f64, f64)>,
}

impl Curves {
    /// Drops the records of steps ≥ `step`: a resumed run logs again the steps after its last
    /// checkpoint, and the later records are the ones the run continued from.
    fn truncate_from(&mut self, step: f64) {
        let keep = self.step.partition_point(|&s| s < step);
        for series in [
            &mut self.step,
            &mut self.loss,
            &mut self.psnr,
            &mut self.obj_psnr,
            &mut self.fg_share,
            &mut self.fg_ari,
        ] {
            series.truncate(keep);
        }
    }
}

/// Parses a JSON-lines training log (`name` is used in errors).
pub fn read_log(text: &str, name: &str) -> Result<Curves> {
    let mut c = Curves::default();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let v: serde_json::Value = serde_json::from_str(line)
            .map_err(|e| anyhow!("{name}: line {}: invalid JSON: {e}", i + 1))?;
        let num = |k: &str| {
            v.get(k)
                .and_then(serde_json::Value::as_f64)
                .unwrap_or(f64::NAN)
        };
        let step = num("step");
        if let Some(eval) = v.get("eval") {
            let get = |k: &str| {
                eval.get(k)
                    .and_then(serde_json::Value::as_f64)
                    .unwrap_or(f64::NAN)
            };
            let keep = c.eval.partition_point(|e| e.0 < step);
            c.eval.truncate(keep);
            c.eval.push((step, get("psnr"), get("fg_ari")));
            continue;
        }
        c.truncate_from(step);
        c.step.push(step);
        c.loss.push(num("loss"));
        c.psnr.push(num("psnr"));
        c.obj_psnr.push(num("obj_psnr"));
        c.fg_share.push(num("fg_share"));
        c.fg_ari.push(num("fg_ari"));
    }
    if c.step.is_empty() {
        bail!("{name}: no training steps in the log");
    }
    Ok(c)
}

/// Centred moving average over `window` points, ignoring NaNs.
fn smooth(values: &[f64], window: usize) -> Vec<f64> {
    let half = window / 2;
    (0..values.len())
        .map(|i| {
            let lo = i.saturating_sub(half);
            let hi = (i + half + 1).min(values.len());
            let ok: Vec<f64> = values[lo..hi]
                .iter()
                .copied()
                .filter(|v| v.is_finite())
                .collect();
            if ok.is_empty() {
                f64::NAN
            } else {
                ok.iter().sum::<f64>() / ok.len() as f64
            }
        })
        .collect()
}

fn range(values: &[&[f64]]) -> (f64, f64) {
    let finite = values
        .iter()
        .flat_map(|v| v.iter())
        .copied()
        .filter(|v| v.is_finite());
    let (lo, hi) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let (lo, hi) = (lo.max(-AXIS_LIMIT), hi.min(AXIS_LIMIT));
    let pad = ((hi - lo) * 0.05).max(1e-9);
    (lo - pad, hi + pad)
}

/// Axes end at ±1e12: a log line with psnr ±1e308 would otherwise make the padded range
/// infinite, and the tick search never end. Values beyond are drawn at the edge.
const AXIS_LIMIT: f64 = 1e12;

/// The step axis: the first to the last finite step (at least one step wide), within
/// ±[`AXIS_LIMIT`].
fn step_axis(steps: &[f64]) -> (f64, f64) {
    let finite = || steps.iter().copied().filter(|v| v.is_finite());
    let lo = finite().fold(f64::INFINITY, f64::min);
    let hi = finite().fold(f64::NEG_INFINITY, f64::max);
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let lo = lo.clamp(-AXIS_LIMIT, AXIS_LIMIT);
    (lo, hi.clamp(-AXIS_LIMIT, AXIS_LIMIT).max(lo + 1.0))
}

/// One run in a picture: its name in the legend and its curves.
#[derive(Debug)]
pub struct Run {
    pub label: String,
    pub curves: Curves,
}

/// Run i's colour when a picture draws several runs (the first eight of Tableau 10).
const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];

/// The most runs one picture draws: one palette colour each.
pub const MAX_RUNS: usize = PALETTE.len();

/// The legend name of a log: its file name without `.log.jsonl` (or `.jsonl`); `stdin` for `-`.
pub fn default_label(path: &str) -> String {
    if crate::io::is_stdio(path) {
        return "stdin".to_string();
    }
    let name = std::path::Path::new(path)
        .file_name()
        .map_or_else(|| path.to_string(), |n| n.to_string_lossy().into_owned());
    [".log.jsonl", ".jsonl"]
        .iter()
        .find_map(|ext| name.strip_suffix(ext).filter(|stem| !stem.is_empty()))
        .map_or_else(|| name.clone(), str::to_string)
}

/// A series of a panel: its name, and its colour when the picture has one run.
struct Series<V> {
    name: &'static str,
    values: V,
    color: RGBColor,
}

/// A per-step series of a run's curves.
type CurveValues = fn(&Curves) -> &[f64];

/// The value of an evaluation (step, novel-view PSNR, FG-ARI) drawn by a series.
type EvalValue = fn(&(f64, f64, f64)) -> f64;

/// How a run's series is drawn: its colour, solid or dashed, and its legend entry.
struct Look {
    color: RGBColor,
    dashed: bool,
    label: String,
}

/// The look of series `series` of run `run`. One run keeps each series' own colour and name, as
/// the single-run picture always has. With several, all of run i's series take colour i, a
/// panel's later series are dashed, and names are prefixed by the run's label.
fn look<V>(runs: &[Run], run: usize, series: usize, s: &Series<V>) -> Look {
    if runs.len() == 1 {
        Look {
            color: s.color,
            dashed: false,
            label: s.name.to_string(),
        }
    } else {
        Look {
            color: PALETTE[run],
            dashed: series > 0,
            label: format!("{}: {}", runs[run].label, s.name),
        }
    }
}

type Chart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;
type Area<'b> = DrawingArea<BitMapBackend<'b>, plotters::coord::Shift>;

fn drawing(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow!("plot: {e}")
}

/// A panel's chart with its caption and axes; `y_label` formats the value axis (plotters'
/// default where `None`).
fn frame<'a, 'b>(
    area: &'a Area<'b>,
    title: &str,
    x: (f64, f64),
    y: (f64, f64),
    y_label: Option<&dyn Fn(&f64) -> String>,
) -> Result<Chart<'a, 'b>> {
    let mut chart = ChartBuilder::on(area)
        .caption(title, ("sans-serif", 16))
        .margin(8)
        .x_label_area_size(28)
        .y_label_area_size(48)
        .build_cartesian_2d(x.0..x.1, y.0..y.1)
        .map_err(drawing)?;
    let step_label = |x: &f64| format!("{x:.0}");
    let mut mesh = chart.configure_mesh();
    mesh.x_desc("step")
        .x_label_formatter(&step_label)
        .label_style(("sans-serif", 11));
    if let Some(y_label) = y_label {
        mesh.y_label_formatter(y_label);
    }
    mesh.draw().map_err(drawing)?;
    Ok(chart)
}

/// Draws a line in `look`, with its legend entry. Points more than an axis' length beyond the
/// chart (values past ±[`AXIS_LIMIT`], an evaluation after the last step is not) are clamped
/// there: the chart clips what lies outside it, and a dashed line's length stays bounded.
fn draw_line(chart: &mut Chart, points: Vec<(f64, f64)>, look: &Look) -> Result<()> {
    let near = |r: std::ops::Range<f64>| {
        let span = r.end - r.start;
        move |v: f64| v.clamp(r.start - span, r.end + span)
    };
    let (x, y) = (near(chart.x_range()), near(chart.y_range()));
    let points: Vec<(f64, f64)> = points.into_iter().map(|(px, py)| (x(px), y(py))).collect();
    let style = look.color.stroke_width(2);
    let anno = if look.dashed {
        chart
            .draw_series(DashedLineSeries::new(points, 6, 4, style))
            .map_err(drawing)?
            .legend(move |(x, y)| DashedPathElement::new(vec![(x, y), (x + 16, y)], 6, 4, style))
    } else {
        chart
            .draw_series(LineSeries::new(points, style))
            .map_err(drawing)?
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], style))
    };
    anno.label(look.label.as_str());
    Ok(())
}

fn draw_legend<'a, 'b: 'a>(chart: &mut Chart<'a, 'b>, position: SeriesLabelPosition) -> Result<()> {
    chart
        .configure_series_labels()
        .position(position)
        .label_font(("sans-serif", 11))
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(drawing)
}

/// A panel of per-step series: each run's raw values faint, its moving average on top.
fn curve_panel(
    area: &Area,
    title: &str,
    series: &[Series<CurveValues>],
    log_y: bool,
    runs: &[Run],
    steps: (f64, f64),
) -> Result<()> {
    let axis = |x: f64| if log_y { x.max(1e-12).log10() } else { x };
    // values[run][series], on the panel's axis.
    let values: Vec<Vec<Vec<f64>>> = runs
        .iter()
        .map(|run| {
            series
                .iter()
                .map(|s| (s.values)(&run.curves).iter().map(|&x| axis(x)).collect())
                .collect()
        })
        .collect();
    let refs: Vec<&[f64]> = values.iter().flatten().map(Vec::as_slice).collect();
    let value_label = |y: &f64| {
        if log_y {
            format!("{:.3}", 10f64.powf(*y))
        } else {
            format!("{y:.2}")
        }
    };
    let mut chart = frame(area, title, steps, range(&refs), Some(&value_label))?;
    for (r, (run, run_values)) in runs.iter().zip(&values).enumerate() {
        let step = &run.curves.step;
        let window = (step.len() / 50).max(1);
        // At most ~1,500 raw points: tens of thousands of overdrawn faint lines add up to a
        // solid band that hides the trend.
        let stride = (step.len() / 1500).max(1);
        for (i, (s, v)) in series.iter().zip(run_values).enumerate() {
            let look = look(runs, r, i, s);
            let raw = step
                .iter()
                .zip(v)
                .step_by(stride)
                .filter(|(_, v)| v.is_finite())
                .map(|(s, v)| (*s, *v));
            chart
                .draw_series(LineSeries::new(raw, look.color.mix(0.12)))
                .map_err(drawing)?;
            let smoothed = step
                .iter()
                .zip(smooth(v, window))
                .filter(|(_, v)| v.is_finite())
                .map(|(s, v)| (*s, v))
                .collect();
            draw_line(&mut chart, smoothed, &look)?;
        }
    }
    draw_legend(&mut chart, SeriesLabelPosition::MiddleRight)
}

/// The held-out evaluations: each run's points joined by lines, FG-ARI scaled to share the
/// PSNR axis.
fn eval_panel(area: &Area, runs: &[Run], steps: (f64, f64)) -> Result<()> {
    if runs.iter().all(|run| run.curves.eval.is_empty()) {
        let text = if runs.len() == 1 {
            "no evaluations in the log"
        } else {
            "no evaluations in the logs"
        };
        return area
            .draw(&Text::new(text, (20, 40), ("sans-serif", 14)))
            .map_err(drawing);
    }
    let series: [Series<EvalValue>; 2] = [
        Series {
            name: "novel-view PSNR",
            values: |e| e.1,
            color: BLUE,
        },
        Series {
            name: "FG-ARI x 40",
            values: |e| e.2 * 40.0,
            color: BLACK,
        },
    ];
    let psnr: Vec<f64> = runs
        .iter()
        .flat_map(|run| run.curves.eval.iter().map(|e| e.1))
        .collect();
    let (lo, hi) = range(&[&psnr]);
    let mut chart = frame(
        area,
        "held-out: novel-view PSNR (dB), FG-ARI x 40",
        steps,
        (lo.min(0.0), hi.max(40.0)),
        None,
    )?;
    for (r, run) in runs.iter().enumerate() {
        for (i, s) in series.iter().enumerate() {
            let look = look(runs, r, i, s);
            let points: Vec<(f64, f64)> = run
                .curves
                .eval
                .iter()
                .map(|e| (e.0, (s.values)(e)))
                .filter(|(_, y)| y.is_finite())
                .collect();
            draw_line(&mut chart, points.clone(), &look)?;
            chart
                .draw_series(
                    points
                        .into_iter()
                        .map(|p| Circle::new(p, 3, look.color.filled())),
                )
                .map_err(drawing)?;
        }
    }
    draw_legend(&mut chart, SeriesLabelPosition::LowerRight)
}

/// Draws the runs (1 to [`MAX_RUNS`]) into an RGB buffer of `width`×`height` and returns it
/// encoded as PNG. The step axis spans all runs.
pub fn plot_png(runs: &[Run], width: u32, height: u32) -> Result<Vec<u8>> {
    if runs.is_empty() || runs.len() > MAX_RUNS {
        bail!("a plot draws 1 to {MAX_RUNS} runs, not {}", runs.len());
    }
    // Registering twice is harmless (same bytes under the same name).
    plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
        .map_err(|_| anyhow!("the bundled font is unreadable"))?;
    let mut buffer = vec![255u8; (3 * width * height) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(drawing)?;
        let panels = root.split_evenly((2, 2));
        let all_steps: Vec<f64> = runs
            .iter()
            .flat_map(|run| run.curves.step.iter().copied())
            .collect();
        let steps = step_axis(&all_steps);
        let series = |name, values: CurveValues, color| Series {
            name,
            values,
            color,
        };
        curve_panel(
            &panels[0],
            "loss",
            &[series("loss", |c| &c.loss, RED)],
            true,
            runs,
            steps,
        )?;
        curve_panel(
            &panels[1],
            "PSNR of sampled rays (dB)",
            &[
                series("all rays", |c| &c.psnr, BLUE),
                series("object rays", |c| &c.obj_psnr, MAGENTA),
            ],
            false,
            runs,
            steps,
        )?;
        curve_panel(
            &panels[2],
            "objects won by foreground slots",
            &[
                series("fg share", |c| &c.fg_share, GREEN),
                series("FG-ARI", |c| &c.fg_ari, BLACK),
            ],
            false,
            runs,
            steps,
        )?;
        eval_panel(&panels[3], runs, steps)?;
        root.present().map_err(drawing)?;
    }
    let rgb: Vec<f32> = buffer.iter().map(|&b| b as f32 / 255.0).collect();
    Ok(crate::image_io::encode_png_rgb(width, height, &rgb))
}

/// `colf-train plot LOG [LOG ...] -o PNG`: draws each log, given as (path, legend name), as
/// one run. At most one path may be stdin (`-`).
pub fn plot_files(logs: &[(&str, String)], output: &str, width: u32, height: u32) -> Result<()> {
    if !(200..=8000).contains(&width) || !(200..=8000).contains(&height) {
        bail!("plot size {width}x{height} is outside 200..=8000");
    }
    if logs
        .iter()
        .filter(|(path, _)| crate::io::is_stdio(path))
        .count()
        > 1
    {
        bail!("only one log can be read from stdin");
    }
    let runs = logs
        .iter()
        .map(|(path, label)| {
            let name = crate::io::display_name(path);
            let text = String::from_utf8(crate::io::read_input(path, false)?)
                .with_context(|| format!("{name}: not UTF-8 text"))?;
            Ok(Run {
                label: label.clone(),
                curves: read_log(&text, name)?,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    crate::io::write_output(output, &plot_png(&runs, width, height)?, true)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(label: &str, log: &str) -> Run {
        Run {
            label: label.to_string(),
            curves: read_log(log, label).unwrap(),
        }
    }

    /// Whether some pixel of the PNG has exactly `color`.
    fn has_color(png: &[u8], color: RGBColor) -> bool {
        let img = crate::image_io::decode_rgb(png, "plot").unwrap();
        let want = [color.0, color.1, color.2].map(|c| c as f32 / 255.0);
        img.data
            .chunks_exact(3)
            .any(|px| px.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-3))
    }

    /// A log of `steps` steps whose loss falls from `loss0`, with one evaluation.
    fn synthetic_log(steps: usize, loss0: f64) -> String {
        let mut log = String::new();
        for i in 0..steps {
            let loss = loss0 / (1.0 + i as f64);
            log += &format!(
                "{{\"step\":{i},\"loss\":{loss},\"psnr\":{},\"obj_psnr\":{},\"fg_share\":0.5,\"fg_ari\":0.4}}\n",
                10.0 + i as f64,
                8.0 + i as f64
            );
        }
        log + &format!("{{\"step\":{steps},\"eval\":{{\"psnr\":20.0,\"fg_ari\":0.5}}}}\n")
    }

    #[test]
    fn several_runs_are_drawn_each_in_its_colour() {
        let one = plot_png(&[run("a", &synthetic_log(40, 1.0))], 600, 400).unwrap();
        // One run keeps the single-run colours: no palette colour.
        assert!(!has_color(&one, PALETTE[0]) && !has_color(&one, PALETTE[1]));
        let runs = [
            run("fused", &synthetic_log(40, 1.0)),
            run("reference", &synthetic_log(60, 2.0)),
        ];
        let two = plot_png(&runs, 600, 400).unwrap();
        assert!(has_color(&two, PALETTE[0]), "run 0's colour is missing");
        assert!(has_color(&two, PALETTE[1]), "run 1's colour is missing");
        assert!(!has_color(&two, PALETTE[2]));
        // A run without evaluations beside one with them.
        let no_eval = Run {
            label: "b".into(),
            curves: read_log(
                "{\"step\":0,\"loss\":1.0}\n{\"step\":5,\"loss\":0.5}\n",
                "b",
            )
            .unwrap(),
        };
        assert!(plot_png(&[run("a", &synthetic_log(9, 1.0)), no_eval], 300, 200).is_ok());
        // One colour per run: more runs than colours are refused, as are none.
        let many: Vec<Run> = (0..=MAX_RUNS)
            .map(|i| run(&i.to_string(), &synthetic_log(3, 1.0)))
            .collect();
        assert!(plot_png(&many[..MAX_RUNS], 300, 200).is_ok());
        let err = plot_png(&many, 300, 200).unwrap_err().to_string();
        assert!(err.contains("1 to 8 runs, not 9"), "{err}");
        assert!(plot_png(&[], 300, 200).is_err());
    }

    #[test]
    fn plot_labels_default_to_file_names() {
        assert_eq!(
            default_label("runs/a/fused.safetensors.log.jsonl"),
            "fused.safetensors"
        );
        assert_eq!(default_label("ref.jsonl"), "ref");
        assert_eq!(default_label("/tmp/train.log"), "train.log");
        assert_eq!(default_label(".jsonl"), ".jsonl");
        assert_eq!(default_label("-"), "stdin");
    }

    #[test]
    fn plot_files_name_the_bad_log_and_refuse_two_stdins() {
        let dir = tempfile::tempdir().unwrap();
        let good = dir.path().join("good.log.jsonl");
        let bad = dir.path().join("bad.log.jsonl");
        std::fs::write(&good, synthetic_log(5, 1.0)).unwrap();
        std::fs::write(&bad, "{\"step\":0}\nnot json\n").unwrap();
        let out = dir.path().join("out.png");
        let out = out.to_str().unwrap();
        let (good, bad) = (good.to_str().unwrap(), bad.to_str().unwrap());
        let err = plot_files(&[(good, "g".into()), (bad, "b".into())], out, 300, 200).unwrap_err();
        let line = format!("{err:#}");
        assert!(
            line.contains("bad.log.jsonl: line 2: invalid JSON"),
            "{line}"
        );
        assert!(!line.contains("good.log.jsonl"), "{line}");
        assert!(
            !std::path::Path::new(out).exists(),
            "output written on failure"
        );
        let err = plot_files(&[("-", "a".into()), ("-", "b".into())], out, 300, 200).unwrap_err();
        assert!(err.to_string().contains("stdin"), "{err}");
        plot_files(&[(good, "g".into()), (good, "again".into())], out, 300, 200).unwrap();
        assert!(std::path::Path::new(out).exists());
    }

    #[test]
    fn reads_steps_and_evaluations() {
        let log = "{\"step\":0,\"loss\":1.0,\"psnr\":5.0,\"obj_psnr\":null,\"fg_share\":0.5,\"fg_ari\":null}\n\
                   {\"step\":1,\"loss\":0.5,\"psnr\":6.0}\n\
                   {\"step\":2,\"eval\":{\"psnr\":20.0,\"fg_ari\":0.3}}\n";
        let c = read_log(log, "log").unwrap();
        assert_eq!(c.step, vec![0.0, 1.0]);
        // A resumed run repeats step 1 and 2: the later records win.
        let resumed = format!(
            "{log}{{\"step\":1,\"loss\":0.4,\"psnr\":7.0}}\n{{\"step\":2,\"loss\":0.3}}\n\
             {{\"step\":2,\"eval\":{{\"psnr\":21.0}}}}\n"
        );
        let r = read_log(&resumed, "log").unwrap();
        assert_eq!(r.step, vec![0.0, 1.0, 2.0]);
        assert_eq!(r.loss, vec![1.0, 0.4, 0.3]);
        assert_eq!(r.eval.len(), 1);
        assert_eq!(r.eval[0].1, 21.0);
        assert!(c.obj_psnr[0].is_nan());
        assert_eq!(c.eval, vec![(2.0, 20.0, 0.3)]);
        let png = plot_png(&[run("log", log)], 400, 300).unwrap();
        let img = crate::image_io::decode_rgb(&png, "plot").unwrap();
        assert_eq!((img.w, img.h), (400, 300));
        // Something was drawn: not every pixel is white.
        assert!(img.data.iter().any(|&v| v < 0.5));
        assert!(read_log("not json\n", "bad.jsonl").is_err());
        assert!(read_log("", "empty.jsonl").is_err());
    }

    #[test]
    fn extreme_values_plot_in_bounded_time() {
        let log = "{\"step\":0,\"loss\":1e308,\"psnr\":1e308}\n\
                   {\"step\":1,\"loss\":-1e308,\"psnr\":-1e308}\n\
                   {\"step\":1e300,\"loss\":0.1,\"psnr\":20}\n\
                   {\"step\":2,\"eval\":{\"psnr\":1e308,\"fg_ari\":-1e308}}\n";
        let curves = read_log(log, "log").unwrap();
        let (lo, hi) = range(&[&curves.psnr]);
        assert!(lo.is_finite() && hi.is_finite() && lo < hi);
        // Several runs: the dashed lines of the later series stay bounded too.
        let started = std::time::Instant::now();
        let png = plot_png(&[run("a", log), run("b", log)], 300, 200).unwrap();
        assert!(!png.is_empty());
        assert!(started.elapsed().as_secs() < 30);
        let started = std::time::Instant::now();
        let png = plot_png(
            &[Run {
                label: "log".into(),
                curves,
            }],
            300,
            200,
        )
        .unwrap();
        assert!(!png.is_empty());
        assert!(started.elapsed().as_secs() < 30);
    }

    #[test]
    fn moving_average_ignores_nan() {
        let s = smooth(&[1.0, f64::NAN, 3.0], 3);
        assert_eq!(s, vec![1.0, 2.0, 3.0]);
    }
}
