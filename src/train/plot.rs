//! A picture of training: loss and PSNR curves drawn from the JSON-lines log (`colf-train plot`).
//!
//! Four panels share the step axis: loss (log scale), PSNR of the sampled rays and of the rays
//! on objects, the foreground share of object rays with FG-ARI, and evaluations (novel-view
//! PSNR on the held-out scenes) where the log has them. Noisy per-step values are drawn faint
//! with a moving average on top.

use anyhow::{anyhow, bail, Context, Result};
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

/// Draws the curves into an RGB buffer of `width`×`height` and returns it encoded as PNG.
pub fn plot_png(c: &Curves, width: u32, height: u32) -> Result<Vec<u8>> {
    // Registering twice is harmless (same bytes under the same name).
    plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
        .map_err(|_| anyhow!("the bundled font is unreadable"))?;
    let mut buffer = vec![255u8; (3 * width * height) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow!("plot: {e}"))?;
        let panels = root.split_evenly((2, 2));
        let steps = step_axis(&c.step);
        let window = (c.step.len() / 50).max(1);
        let faint = |color: RGBColor| color.mix(0.12);
        let panel = |area: &DrawingArea<BitMapBackend, plotters::coord::Shift>,
                     title: &str,
                     series: &[(&str, &[f64], RGBColor)],
                     log_y: bool|
         -> Result<()> {
            let transformed: Vec<Vec<f64>> = series
                .iter()
                .map(|(_, v, _)| {
                    v.iter()
                        .map(|x| if log_y { x.max(1e-12).log10() } else { *x })
                        .collect()
                })
                .collect();
            let refs: Vec<&[f64]> = transformed.iter().map(Vec::as_slice).collect();
            let (lo, hi) = range(&refs);
            let mut chart = ChartBuilder::on(area)
                .caption(title, ("sans-serif", 16))
                .margin(8)
                .x_label_area_size(28)
                .y_label_area_size(48)
                .build_cartesian_2d(steps.0..steps.1, lo..hi)
                .map_err(|e| anyhow!("plot: {e}"))?;
            chart
                .configure_mesh()
                .x_desc("step")
                .x_label_formatter(&|x| format!("{x:.0}"))
                .y_label_formatter(&|y| {
                    if log_y {
                        format!("{:.3}", 10f64.powf(*y))
                    } else {
                        format!("{y:.2}")
                    }
                })
                .label_style(("sans-serif", 11))
                .draw()
                .map_err(|e| anyhow!("plot: {e}"))?;
            for ((label, _, color), values) in series.iter().zip(&transformed) {
                // At most ~1,500 raw points: tens of thousands of overdrawn faint lines add
                // up to a solid band that hides the trend.
                let stride = (c.step.len() / 1500).max(1);
                let raw = c
                    .step
                    .iter()
                    .zip(values)
                    .step_by(stride)
                    .filter(|(_, v)| v.is_finite())
                    .map(|(s, v)| (*s, *v));
                chart
                    .draw_series(LineSeries::new(raw, faint(*color)))
                    .map_err(|e| anyhow!("plot: {e}"))?;
                let smoothed = smooth(values, window);
                let line = c
                    .step
                    .iter()
                    .zip(smoothed)
                    .filter(|(_, v)| v.is_finite())
                    .map(|(s, v)| (*s, v));
                let color = *color;
                chart
                    .draw_series(LineSeries::new(line, color.stroke_width(2)))
                    .map_err(|e| anyhow!("plot: {e}"))?
                    .label(*label)
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
                    });
            }
            chart
                .configure_series_labels()
                .label_font(("sans-serif", 11))
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(|e| anyhow!("plot: {e}"))?;
            Ok(())
        };
        panel(&panels[0], "loss", &[("loss", &c.loss, RED)], true)?;
        panel(
            &panels[1],
            "PSNR of sampled rays (dB)",
            &[
                ("all rays", &c.psnr, BLUE),
                ("object rays", &c.obj_psnr, MAGENTA),
            ],
            false,
        )?;
        panel(
            &panels[2],
            "objects won by foreground slots",
            &[
                ("fg share", &c.fg_share, GREEN),
                ("FG-ARI", &c.fg_ari, BLACK),
            ],
            false,
        )?;
        let eval_steps: Vec<f64> = c.eval.iter().map(|e| e.0).collect();
        let eval_psnr: Vec<f64> = c.eval.iter().map(|e| e.1).collect();
        let eval_ari: Vec<f64> = c.eval.iter().map(|e| e.2).collect();
        if c.eval.is_empty() {
            panels[3]
                .draw(&Text::new(
                    "no evaluations in the log",
                    (20, 40),
                    ("sans-serif", 14),
                ))
                .map_err(|e| anyhow!("plot: {e}"))?;
        } else {
            let (lo, hi) = range(&[&eval_psnr]);
            let mut chart = ChartBuilder::on(&panels[3])
                .caption(
                    "held-out: novel-view PSNR (dB), FG-ARI x 40",
                    ("sans-serif", 16),
                )
                .margin(8)
                .x_label_area_size(28)
                .y_label_area_size(48)
                .build_cartesian_2d(steps.0..steps.1, lo.min(0.0)..hi.max(40.0))
                .map_err(|e| anyhow!("plot: {e}"))?;
            chart
                .configure_mesh()
                .x_desc("step")
                .x_label_formatter(&|x| format!("{x:.0}"))
                .label_style(("sans-serif", 11))
                .draw()
                .map_err(|e| anyhow!("plot: {e}"))?;
            let pts = |v: &[f64], scale: f64| -> Vec<(f64, f64)> {
                eval_steps
                    .iter()
                    .zip(v)
                    .filter(|(_, y)| y.is_finite())
                    .map(|(s, y)| (*s, y * scale))
                    .collect()
            };
            for (label, values, scale, color) in [
                ("novel-view PSNR", &eval_psnr, 1.0, BLUE),
                ("FG-ARI x 40", &eval_ari, 40.0, BLACK),
            ] {
                let points = pts(values, scale);
                chart
                    .draw_series(LineSeries::new(points.clone(), color.stroke_width(2)))
                    .map_err(|e| anyhow!("plot: {e}"))?
                    .label(label)
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
                    });
                chart
                    .draw_series(
                        points
                            .into_iter()
                            .map(|p| Circle::new(p, 3, color.filled())),
                    )
                    .map_err(|e| anyhow!("plot: {e}"))?;
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::LowerRight)
                .label_font(("sans-serif", 11))
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(|e| anyhow!("plot: {e}"))?;
        }
        root.present().map_err(|e| anyhow!("plot: {e}"))?;
    }
    let rgb: Vec<f32> = buffer.iter().map(|&b| b as f32 / 255.0).collect();
    Ok(crate::image_io::encode_png_rgb(width, height, &rgb))
}

/// `colf-train plot LOG -o PNG`.
pub fn plot_file(log: &str, output: &str, width: u32, height: u32) -> Result<()> {
    if !(200..=8000).contains(&width) || !(200..=8000).contains(&height) {
        bail!("plot size {width}x{height} is outside 200..=8000");
    }
    let text = String::from_utf8(crate::io::read_input(log, false)?)
        .with_context(|| format!("{}: not UTF-8 text", crate::io::display_name(log)))?;
    let curves = read_log(&text, crate::io::display_name(log))?;
    crate::io::write_output(output, &plot_png(&curves, width, height)?, true)
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let png = plot_png(&c, 400, 300).unwrap();
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
        let started = std::time::Instant::now();
        let png = plot_png(&curves, 300, 200).unwrap();
        assert!(!png.is_empty());
        assert!(started.elapsed().as_secs() < 30);
    }

    #[test]
    fn moving_average_ignores_nan() {
        let s = smooth(&[1.0, f64::NAN, 3.0], 3);
        assert_eq!(s, vec![1.0, 2.0, 3.0]);
    }
}
