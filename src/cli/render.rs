//! `colf-render`: codes + cameras → images, masks and EXR layers.

use clap::Parser;

/// Render an encoded (and perhaps edited) scene from any cameras.
#[derive(Parser, Debug)]
#[command(
    name = "colf-render",
    version,
    about = "Render a colf codes file from the cameras of a transforms.json",
    long_about = "Render every frame of CAMERAS (a transforms.json: camera-to-world, OpenGL \
camera axes, world +Z up) from a codes file. Each slot's light field is evaluated once per ray \
in its own frame (slot_to_world), the background in world space, and the compositor blends them \
by their ordering values. A model whose slots cast shadows (shadow head) darkens the background \
by them, reading each slot's light field once more along the light when it has a shadow light; \
--no-shadows leaves them out.\n\n\
Outputs, for a frame whose file_path stem is S (else frame_NNNN, NNNN = the frame index):\n\n\
  DIR/S.png        8-bit sRGB RGB\n\n\
  DIR/S.mask.png   with --masks: 8-bit grey, 0 = background, k + 1 = slot k (argmax of the \
compositor weights)\n\n\
  DIR/S.exr        with --exr: float channels R, G, B; bg.weight and bg.order for the \
background; slotK.weight and slotK.order for slot K (compositor weight in [0, 1] and the \
world-comparable ordering value)\n\n\
Masks hold 8-bit labels while K < 255 and 16-bit labels beyond. Every file is written \
atomically (a frame's files appear together, after the frame is rendered) and replaces \
whatever is at its path in DIR: a symbolic link there is replaced, never followed, so nothing is \
written outside DIR. SIGINT or SIGTERM \
removes the temporary files and exits 130 or 143, leaving finished frames intact. A progress \
line per frame goes to stderr (-q silences it). Codes encoded by another model are refused. The \
hypernetwork runs once per slot per run; rays are evaluated in chunks of a few hundred, one chunk \
per thread at a time, and the output does not depend on the number of threads. An exact render \
is rendered and written in bands of about 65536 pixels, the PNG and mask streamed row by row, so \
its memory does not grow with the image size; with --exr a frame's float channels, 4 x (5 + 2K) \
bytes a pixel, are gathered before its EXR is written, and --adaptive renders a whole frame at \
once (docs/reliability.md has the measured figures).\n\n\
Without --adaptive the render is exact. --adaptive [EPS] first renders the compositor weights \
(and the shadows slots cast) at 1/4 resolution, dilates each slot's maps by one coarse pixel, \
and then evaluates a slot at full resolution only where its weight exceeds EPS (default 0.03), \
and its shadow only where the shadow's density does; the background is always evaluated. A \
slot left out of a pixel has weight 0 and ordering value +inf in the EXR. The speed/accuracy \
trade is measured in docs/tradeoff.md.\n\n\
A volumetric model (colf-train init --preset volumetric: the uORF-style baseline) is rendered \
by sampling --samples N points per ray (default: the model's, 64); its EXR ordering channel \
holds each slot's expected depth along the ray. --frames A..B renders a subset (half-open, like Rust ranges: 0..10 \
is frames 0 to 9; A.. and ..B work too) so batches can be split across processes.\n\n\
The model is --model, else $COLF_MODEL, else the default model bundled with colf.",
    after_help = "Examples:\n  colf-render scene.codes --cameras transforms.json --out renders/ --masks\n  \
colf-cameras orbit --frames 36 | colf-render scene.codes --cameras - --out orbit/\n  \
colf-edit moves.json scene.codes | colf-render --cameras orbit.json --out moved/ --exr"
)]
pub struct RenderArgs {
    /// Codes file (`-` or omitted: stdin).
    #[arg(value_name = "CODES")]
    pub codes: Option<String>,

    /// transforms.json with the cameras to render (`-`: stdin).
    #[arg(long, value_name = "CAMERAS.json")]
    pub cameras: String,

    /// Output folder (created if missing).
    #[arg(long, value_name = "DIR", value_parser = clap::builder::NonEmptyStringValueParser::new())]
    pub out: String,

    /// Also write DIR/S.mask.png segmentation masks.
    #[arg(long)]
    pub masks: bool,

    /// Also write DIR/S.exr with float RGB and per-slot weight and ordering channels.
    #[arg(long)]
    pub exr: bool,

    /// Render only frames A..B (half-open; `A..`, `..B`, or a single index N).
    #[arg(long, value_name = "A..B", value_parser = crate::render::FrameSelection::parse)]
    pub frames: Option<crate::render::FrameSelection>,

    /// Model file, or a bundled model's name (`default`, `supervised`, `blender`); default: $COLF_MODEL, else
    /// the bundled default model.
    #[arg(long, value_name = "M")]
    pub model: Option<String>,

    /// Adaptive rendering: render the compositor weights and shadows at 1/4 resolution first,
    /// then evaluate each slot at full resolution only where its dilated coarse weight exceeds
    /// EPS, and its shadow where the shadow's coarse density does (the background always). Bare
    /// --adaptive uses EPS = 0.03. Light-field models only.
    #[arg(long, value_name = "EPS", num_args = 0..=1, default_missing_value = "0.03",
          value_parser = crate::cli::parse::non_negative_f32)]
    pub adaptive: Option<f32>,

    /// Samples per ray of a volumetric (baseline) model (default: the model's, 64 for the
    /// `volumetric` preset). Refused for light-field models.
    #[arg(long, value_name = "N", value_parser = crate::cli::parse::samples)]
    pub samples: Option<usize>,

    /// Leave out the shadows foreground slots cast on the background (models with a shadow
    /// head): faster (one light-field evaluation per ray and slot instead of two when the
    /// shadows are read along the light), with the background undarkened. No effect on models
    /// without shadows.
    #[arg(long)]
    pub no_shadows: bool,

    /// No per-frame progress lines on stderr.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Runs `colf-render`.
pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    use crate::camera::Cameras;
    use crate::codes::Codes;
    use crate::io::display_name;
    use crate::render::output::FrameFiles;
    use crate::render::PreparedScene;
    use anyhow::Context;
    use std::path::Path;

    let codes_path = args.codes.as_deref().unwrap_or("-");
    if codes_path == "-" && args.cameras == "-" {
        return Err(crate::cli::both_stdin("CODES", "--cameras"));
    }
    let codes = Codes::read(codes_path)?;
    let cameras = Cameras::read(&args.cameras)?;
    let range = match &args.frames {
        Some(selection) => selection
            .resolve(cameras.frames.len())
            .with_context(|| display_name(&args.cameras).to_string())?,
        None => 0..cameras.frames.len(),
    };
    // Output names, checked up front: no two outputs may be the same file.
    let names: Vec<String> = range
        .clone()
        .map(|i| {
            cameras.frames[i]
                .stem()
                .unwrap_or_else(|| format!("frame_{i:04}"))
        })
        .collect();
    check_output_names(&names, range.start, args.masks, args.exr)
        .with_context(|| display_name(&args.cameras).to_string())?;
    let model = crate::cli::model_path::load_model(args.model.as_deref())?;
    let mut scene = PreparedScene::new(&model, &codes, display_name(codes_path))?;
    if args.no_shadows {
        scene.drop_shadows();
    }
    let opts = crate::render::RenderOptions {
        samples: args.samples,
        adaptive: args.adaptive,
    };
    scene.check_options(&opts)?;
    let out_dir = Path::new(&args.out);
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("{}: cannot create the output folder", args.out))?;
    let total = names.len();
    for (n, (index, name)) in range.zip(&names).enumerate() {
        let started = std::time::Instant::now();
        let camera = &cameras.frames[index];
        let (width, height) = (camera.intrinsics.w, camera.intrinsics.h);
        let mut files = FrameFiles::create(
            out_dir,
            name,
            (width, height),
            scene.num_slots(),
            args.masks,
            args.exr,
        )?;
        let stats = if opts.adaptive.is_some() {
            // The adaptive render's coarse pass sees the whole frame.
            let (frame, stats) = scene
                .render_frame_with(camera, &opts)
                .with_context(|| format!("frame {index}"))?;
            files.write_band(&frame)?;
            stats
        } else {
            // Exact: rendered and written in bands of rows, so memory does not grow with the
            // image (but for the EXR's channels).
            let rows = (BAND_PIXELS / width as usize).max(1) as u32;
            for start in (0..height).step_by(rows as usize) {
                let band = scene
                    .render_rows(camera, start..(start + rows).min(height), &opts)
                    .with_context(|| format!("frame {index}"))?;
                files.write_band(&band)?;
            }
            None
        };
        files.commit()?;
        if !args.quiet {
            let adaptive = stats.map_or(String::new(), |s| {
                format!(
                    ", adaptive: {:.0} % of slot evaluations",
                    100.0 * s.evaluated as f64 / s.possible.max(1) as f64
                )
            });
            eprintln!(
                "colf-render: {}/{total} {name} ({}x{}, {} slots) {:.0} ms{adaptive}",
                n + 1,
                width,
                height,
                scene.num_slots(),
                started.elapsed().as_secs_f64() * 1e3
            );
        }
    }
    Ok(())
}

/// Pixels rendered and written at a time by an exact render: a band of rows of about this
/// many pixels (a few MB of working memory whatever the image size).
const BAND_PIXELS: usize = 1 << 16;

/// The files frame `first + n` writes (`S.png`, and `S.mask.png`, `S.exr` when asked), for
/// stems `names`; an error names the two frames that would write the same file (`x` and
/// `x.mask` with --masks both write `x.mask.png`).
pub fn check_output_names(
    names: &[String],
    first: usize,
    masks: bool,
    exr: bool,
) -> anyhow::Result<()> {
    let mut seen = std::collections::BTreeMap::new();
    for (n, name) in names.iter().enumerate() {
        let files = [
            Some(format!("{name}.png")),
            masks.then(|| format!("{name}.mask.png")),
            exr.then(|| format!("{name}.exr")),
        ];
        for file in files.into_iter().flatten() {
            if let Some(other) = seen.insert(file.clone(), first + n) {
                anyhow::bail!(
                    "frames {other} and {} would both write `{file}` (give frames distinct file_path stems)",
                    first + n
                );
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_output_file_name_is_checked_for_clashes() {
        let names = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        assert!(check_output_names(&names(&["x", "x.mask"]), 0, false, true).is_ok());
        let msg = check_output_names(&names(&["x", "x.mask"]), 3, true, false)
            .unwrap_err()
            .to_string();
        assert!(
            msg.contains("frames 3 and 4") && msg.contains("x.mask.png"),
            "{msg}"
        );
        assert!(check_output_names(&names(&["a", "a"]), 0, false, false).is_err());
        assert!(check_output_names(&names(&["a", "b"]), 0, true, true).is_ok());
    }

    #[test]
    fn an_empty_output_folder_is_a_usage_error() {
        let err = RenderArgs::try_parse_from(["colf-render", "c", "--cameras", "t", "--out", ""])
            .unwrap_err();
        assert_eq!(err.exit_code(), 2);
    }

    #[test]
    fn bare_adaptive_uses_the_recommended_eps() {
        let args = RenderArgs::try_parse_from([
            "colf-render",
            "c.codes",
            "--cameras",
            "t.json",
            "--out",
            "o",
            "--adaptive",
        ])
        .unwrap();
        assert_eq!(
            args.adaptive,
            Some(crate::render::adaptive::RECOMMENDED_EPS)
        );
    }
}
