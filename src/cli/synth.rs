//! `colf-synth`: multi-view synthetic scenes with ground truth.

use crate::synth::blender::{BlenderOptions, DEFAULT_SAMPLES};
use crate::synth::{Engine, MoveSpec, OutputLayout, Preset, Progress, Split, SynthOptions};
use clap::Parser;
use std::path::PathBuf;

/// Render multi-view synthetic scenes with exact object masks and cameras.
#[derive(Parser, Debug, Clone)]
#[command(
    name = "colf-synth",
    version,
    about = "Render multi-view synthetic scenes (CLEVR-567 and friends) with masks and cameras",
    long_about = "Render multi-view synthetic scenes with an analytic ray tracer: CLEVR shapes \
(or cars, or chairs in a room) on a ground plane, one directional light with hard shadows, Lambertian shading, \
anti-aliased 8-bit sRGB images, exact object masks and NeRF-convention cameras. With \
--engine blender the same scenes (objects and cameras) of clevr567, packed11, room-chair or \
room-diverse are rendered by Blender's Cycles instead (CPU path tracing, three area lights, soft \
shadows).\n\n\
Each scene goes to DIR/scene_NNNNN/ (index zero-padded to 5 digits) and holds view_NNN.png, \
view_NNN.mask.png (8-bit grey: 0 = background, k = object k of scene.json, 1-based), \
transforms.json (camera-to-world, OpenGL camera axes, world +Z up) and scene.json (objects, \
light, ground, camera placements, per-view visible pixels of each object). DIR/dataset.json \
records the options, written last.\n\n\
The same options give byte-identical files, whatever the number of threads. Scene i of a \
split is drawn from its own seed stream, derived from (--seed, --split, i): train and test \
never share a scene, and scene i does not depend on --scenes, so a bigger set extends a \
smaller one.\n\n\
Presets: clevr567 (5-7 CLEVR shapes on a grey floor, cameras at distance 12.4, elevation 40 \
degrees, uniform azimuth; the reference distribution), packed11 (exactly 11 shapes in the same \
area), clevr567-textured (clevr567 on a procedural checker/noise floor), city (a long street \
with 2-4 rows of boxy cars in two lanes, buildings and sky; each view stands in front of a row \
of cars, in a lane, 0.4-2 units high, looking down the street), city-block (the paper's \
City-Block: one street, the same buildings and light in every scene, two rows of cars 20 units \
apart anywhere along it; views 0 and 1 are the rows' context views, 9 units in front of their \
row, the others stand anywhere from the block's start to 5 units before the back row), room-chair (after uORF's \
Room-Chair: 3-4 chairs of one procedural design in a walled 16 x 16 room on one of 3 floor \
textures; cameras at distance 8.5, elevation 35 degrees, uniform azimuth, looking at the room's \
centre), room-diverse (after uORF's Room-Diverse: as room-chair with chairs of 1200 procedural \
designs and 50 floor textures); --randomize-camera varies the CLEVR presets' camera distance \
and elevation. Cameras are redrawn (up to 20 times) until every object covers \
a mask pixel in some view.\n\n\
Without --scenes the paper's dataset size is generated: 1000 train and 500 test scenes \
(room-diverse: 5000 train; city-block: 500 train, and its test split needs --scenes).",
    after_help = "Examples:\n  colf-synth --out data/train --scenes 1000\n  \
colf-synth --out data/test --scenes 100 --split test --size 128\n  \
colf-synth --out data/room-diverse-test --preset room-diverse --split test --size 128\n  \
colf-synth --out data/moved --scenes 10 --split test --move 2 1.5 -0.5"
)]
pub struct SynthArgs {
    /// Output folder (created); scenes go to DIR/scene_NNNNN/.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Number of scenes (default: the paper's count for the preset and split — 1000 train and
    /// 500 test scenes, room-diverse 5000 train; city has none and needs --scenes).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    pub scenes: Option<u32>,
    /// Base seed of the split's seed streams.
    #[arg(long, value_name = "S", default_value_t = 0)]
    pub seed: u64,
    /// Image width and height in pixels (the contract sizes are 64 and 128).
    #[arg(long, value_name = "PX", default_value_t = 64,
          value_parser = clap::value_parser!(u32).range(8..=4096))]
    pub size: u32,
    /// Views per scene.
    #[arg(long, value_name = "V", default_value_t = 4,
          value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub views: u32,
    /// Scene distribution.
    #[arg(long, value_enum, default_value_t = Preset::Clevr567)]
    pub preset: Preset,
    /// Which seed stream: train and test scenes are disjoint.
    #[arg(long, value_enum, default_value_t = Split::Train)]
    pub split: Split,
    /// Also render every view with object K (1-based, as in the masks) moved by (DX, DY, 0)
    /// world units, as view_NNN.moved.png and view_NNN.moved.mask.png (in uORF's layout, also
    /// the files of uORF's scene-manipulation loader, see --layout).
    #[arg(long = "move", num_args = 3, value_names = ["K", "DX", "DY"],
          allow_negative_numbers = true)]
    pub move_object: Option<Vec<f64>>,
    /// Renderer: the built-in analytic ray tracer, or Blender's Cycles (CPU; clevr567,
    /// packed11, room-chair and room-diverse only; needs Blender 3.x, `apt-get install
    /// blender`; the executable is `blender` on PATH or the COLF_BLENDER environment
    /// variable).
    #[arg(long, value_enum, default_value_t = EngineName::Analytic)]
    pub engine: EngineName,
    /// File layout: colf's scene folders, or uORF's flat files as uORF's own loaders read them
    /// ({i:05}_sc{s:04}_az{v:02}.png, _mask.png with the background at grey 64 and one object
    /// below it, _RT.txt, _azi_rot.txt; with --move, _moved.png, _changed.png,
    /// _providing_bg.png, _mask_for_moving.png, _mask_for_bg.png, _mask_for_providing_bg.png
    /// and NNN_movement.txt); see docs/synth.md.
    #[arg(long, value_enum, default_value_t = OutputLayout::Colf)]
    pub layout: OutputLayout,
    /// Blender engine: path-tracing samples per pixel (no denoising).
    #[arg(long, value_name = "N", default_value_t = DEFAULT_SAMPLES,
          value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub samples: u32,
    /// Blender engine: Blender processes at once, each on one thread (default: the number
    /// of CPUs).
    #[arg(short = 'j', long, value_name = "N",
          value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub jobs: Option<u32>,
    /// Analytic engine: randomise each scene's look — floor albedo 0.25-0.75 (uniform
    /// floors), light azimuth 0-360 and elevation 30-75 degrees, ambient 0.2-0.5 and direct
    /// 0.45-0.85 shares, light radius 0-8 degrees (soft shadows), exposure 2^(-0.5..0.5),
    /// sensor noise sigma 0-0.02 — from a stream of its own: objects and cameras stay as
    /// without it.
    #[arg(long)]
    pub randomize_look: bool,
    /// CLEVR presets (clevr567, packed11, clevr567-textured), any engine: vary each view's
    /// camera — distance 12.4 times 0.8-1.25 and elevation 25-55 degrees, still looking at
    /// the centre — from a stream of its own: objects and light stay as without it (and the
    /// azimuths, unless a view had to be redrawn).
    #[arg(long)]
    pub randomize_camera: bool,
    /// Write into a folder that is not empty: the files of an earlier colf-synth run there
    /// (dataset.json, scene_NNNNN folders, uORF-layout files) are removed first, other files
    /// are left alone. Without it a non-empty folder is refused, so stale scenes cannot mix
    /// with new ones.
    #[arg(long, conflicts_with = "resume")]
    pub force: bool,
    /// Continue an interrupted run of the same command in its folder: complete scenes are
    /// kept (each checked against what these options make; a scene made by other options
    /// stops the run before anything is written), unfinished ones are rendered again, and
    /// dataset.json is written at the end. The result is byte for byte that of an
    /// uninterrupted run.
    #[arg(long)]
    pub resume: bool,
    /// No progress on stderr.
    #[arg(short, long)]
    pub quiet: bool,
}

/// `--engine`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum EngineName {
    /// The built-in analytic ray tracer.
    Analytic,
    /// Blender's Cycles.
    Blender,
}

impl SynthArgs {
    /// Checks what clap cannot; the message is a usage error (exit 2).
    pub fn validate(&self) -> Result<(), String> {
        self.move_spec()?;
        if self.engine == EngineName::Blender && self.randomize_look {
            return Err("--randomize-look works with --engine analytic only".to_string());
        }
        if self.randomize_camera && !self.preset.varies_cameras() {
            return Err(format!(
                "--randomize-camera varies the cameras of clevr567, packed11 and \
                 clevr567-textured, not {}",
                self.preset.name()
            ));
        }
        if self.engine == EngineName::Blender && !crate::synth::blender::supports(self.preset) {
            return Err(format!(
                "--engine blender renders --preset clevr567, packed11, room-chair or \
                 room-diverse, not {}",
                self.preset.name()
            ));
        }
        self.scene_count()?;
        Ok(())
    }

    /// `--scenes`, or the paper's count for the preset and split.
    pub fn scene_count(&self) -> Result<u64, String> {
        match (self.scenes, self.preset.paper_scenes(self.split)) {
            (Some(n), _) => Ok(n as u64),
            (None, Some(n)) => Ok(n),
            (None, None) => Err(format!(
                "--preset {} has no paper dataset size: give --scenes N",
                self.preset.name()
            )),
        }
    }

    /// The library's options (after [`SynthArgs::validate`]).
    pub fn options(&self) -> Result<SynthOptions, String> {
        Ok(SynthOptions {
            out: self.out.clone(),
            scenes: self.scene_count()?,
            seed: self.seed,
            size: self.size,
            views: self.views as usize,
            preset: self.preset,
            split: self.split,
            moved: self.move_spec()?,
            engine: match self.engine {
                EngineName::Analytic => Engine::Analytic,
                EngineName::Blender => Engine::Blender(BlenderOptions {
                    executable: std::env::var_os("COLF_BLENDER")
                        .filter(|v| !v.is_empty())
                        .map_or_else(|| "blender".into(), Into::into),
                    samples: self.samples,
                    jobs: self.jobs.map_or_else(
                        || std::thread::available_parallelism().map_or(1, |n| n.get()),
                        |j| j as usize,
                    ),
                }),
            },
            layout: self.layout,
            randomize_look: self.randomize_look,
            randomize_camera: self.randomize_camera,
            replace: self.force,
            resume: self.resume,
        })
    }

    /// The checked `--move`, if given.
    pub fn move_spec(&self) -> Result<Option<MoveSpec>, String> {
        let Some(values) = &self.move_object else {
            return Ok(None);
        };
        let [k, dx, dy] = values[..] else {
            return Err(format!(
                "--move takes 3 values K DX DY, got {}",
                values.len()
            ));
        };
        if !(k >= 1.0 && k.fract() == 0.0 && k <= 255.0) {
            return Err(format!(
                "--move: object K = {k} must be a whole number in 1..=255 (1-based, as in the masks)"
            ));
        }
        if !dx.is_finite() || !dy.is_finite() {
            return Err("--move: DX and DY must be finite numbers".to_string());
        }
        Ok(Some(MoveSpec {
            object: k as usize,
            dx,
            dy,
        }))
    }
}

/// Runs `colf-synth`: progress on stderr (a counter on a terminal, every tenth otherwise)
/// unless `--quiet`, and a summary line at the end.
pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    use anyhow::Context;
    use std::io::IsTerminal;
    let options = args.options().map_err(anyhow::Error::msg)?;
    let terminal = std::io::stderr().is_terminal();
    let quiet = args.quiet;
    let report = move |p: Progress| {
        if quiet {
            return;
        }
        let Progress { done: k, total: n } = p;
        if terminal {
            eprint!("\rcolf-synth: {k}/{n} scenes");
        } else if k == n || (k * 10 / n) != ((k - 1) * 10 / n) {
            eprintln!("colf-synth: {k}/{n} scenes");
        }
    };
    if let Some(m) = options.moved {
        crate::synth::check_moved_object(&options)
            .with_context(|| format!("--move {}", m.object))?;
    }
    if !options.replace && !options.resume {
        crate::synth::clear_output(&options.out, false).map_err(|e| {
            anyhow::anyhow!(
                "{e:#} (--force replaces an earlier run's scenes, --resume continues it)"
            )
        })?;
    }
    let start = std::time::Instant::now();
    let result = crate::synth::run(&options, &report);
    if !quiet && terminal {
        eprintln!();
    }
    let n = result?;
    if !quiet {
        eprintln!(
            "colf-synth: wrote {n} {} scenes to {} in {:.1} s",
            args.preset.name(),
            args.out.display(),
            start.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_defaults_and_move() {
        let a = SynthArgs::try_parse_from(["colf-synth", "--out", "x", "--scenes", "3"]).unwrap();
        assert_eq!(a.scene_count(), Ok(3));
        assert_eq!((a.seed, a.size, a.views), (0, 64, 4));
        assert_eq!((a.preset, a.split), (Preset::Clevr567, Split::Train));
        assert_eq!(a.move_spec().unwrap(), None);
        let a = SynthArgs::try_parse_from([
            "colf-synth",
            "--out",
            "x",
            "--scenes",
            "3",
            "--move",
            "2",
            "-1.5",
            "0.25",
            "--preset",
            "clevr567-textured",
        ])
        .unwrap();
        assert_eq!(
            a.move_spec().unwrap(),
            Some(MoveSpec {
                object: 2,
                dx: -1.5,
                dy: 0.25
            })
        );
        assert_eq!(a.preset, Preset::Clevr567Textured);
    }

    #[test]
    fn rejects_bad_values() {
        for bad in [
            vec!["--scenes", "0"],
            vec!["--scenes", "2", "--size", "4"],
            vec!["--scenes", "2", "--preset", "nope"],
            vec!["--scenes", "2", "--move", "1", "2"],
        ] {
            let mut argv = vec!["colf-synth", "--out", "x"];
            argv.extend(bad.iter().copied());
            assert!(SynthArgs::try_parse_from(&argv).is_err(), "{argv:?}");
        }
        let a = SynthArgs::try_parse_from([
            "colf-synth",
            "--out",
            "x",
            "--scenes",
            "2",
            "--move",
            "1.5",
            "0",
            "0",
        ])
        .unwrap();
        assert!(a.validate().unwrap_err().contains("whole number"));
    }

    #[test]
    fn the_scene_count_defaults_to_the_papers() {
        let count = |extra: &[&str]| {
            let mut argv = vec!["colf-synth", "--out", "x"];
            argv.extend(extra);
            let a = SynthArgs::try_parse_from(&argv).unwrap();
            a.validate().and_then(|_| a.scene_count())
        };
        assert_eq!(count(&[]), Ok(1000));
        assert_eq!(count(&["--split", "test"]), Ok(500));
        assert_eq!(count(&["--preset", "room-chair"]), Ok(1000));
        assert_eq!(
            count(&["--preset", "room-chair", "--split", "test"]),
            Ok(500)
        );
        assert_eq!(count(&["--preset", "room-diverse"]), Ok(5000));
        assert_eq!(
            count(&["--preset", "room-diverse", "--split", "test"]),
            Ok(500)
        );
        assert_eq!(count(&["--preset", "room-diverse", "--scenes", "7"]), Ok(7));
        assert!(count(&["--preset", "city"])
            .unwrap_err()
            .contains("--scenes"));
        assert_eq!(count(&["--preset", "city", "--scenes", "2"]), Ok(2));
    }
}
