//! Command-line definitions of every colf stage, and the glue that runs a stage body with the
//! project's conventions (one error line, exit codes 0/1/2). The man pages in `man/` are
//! generated from these definitions (`tests/man_pages.rs`), so they cannot drift from `--help`.

pub mod cameras;
pub mod edit;
pub mod encode;
pub mod eval;
pub mod model_path;
pub mod render;
pub mod sheet;
pub mod synth;
pub mod train;

/// Runs the body of stage `colf-<stage>`: exit 0 on success; on error, one line
/// `colf-<stage>: error: <cause chain>` on stderr and exit 1. Usage errors are clap's (exit 2).
/// SIGINT and SIGTERM remove the stage's temporary files and exit 130 and 143
/// (`io::install_signal_cleanup`); a body that returns `io::Interrupted` (colf-train, after its
/// checkpoint) exits the same way.
pub fn run(stage: &str, body: impl FnOnce() -> anyhow::Result<()>) -> ! {
    crate::alloc::tune_for_tensors();
    crate::alloc::tune_thread_pools();
    let result = crate::io::install_signal_cleanup(stage).and_then(|()| body());
    match result {
        Ok(()) => std::process::exit(0),
        Err(err) if err.downcast_ref::<UsageError>().is_some() => {
            eprintln!("colf-{stage}: error: {err:#}\n\nFor more information, try '--help'.");
            std::process::exit(2)
        }
        Err(err) if err.downcast_ref::<crate::io::Interrupted>().is_some() => {
            let interrupted = *err
                .downcast_ref::<crate::io::Interrupted>()
                .expect("checked");
            eprintln!("colf-{stage}: {err:#}");
            std::process::exit(interrupted.exit_code())
        }
        Err(_) if crate::io::exiting_on_signal() => loop {
            // The signal thread reports the interruption and exits; this error is its effect.
            std::thread::park();
        },
        Err(err) => {
            // `{:#}` joins the context chain on one line: "file: what: why".
            let line = format!("{err:#}").replace('\n', " ");
            eprintln!("colf-{stage}: error: {line}");
            std::process::exit(1)
        }
    }
}

/// A usage error found after parsing (two inputs on stdin): `run` exits 2, as for clap's.
#[derive(Debug)]
pub struct UsageError(pub String);

impl std::fmt::Display for UsageError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}

/// The usage error for two inputs that both name stdin (`-`).
pub fn both_stdin(first: &str, second: &str) -> anyhow::Error {
    UsageError(format!("{first} and {second} cannot both be stdin (`-`)")).into()
}

/// Value parsers for clap: range checks belong in parsing, so a bad value is a usage error
/// (exit 2) naming the flag.
pub mod parse {
    fn number<T: std::str::FromStr>(text: &str) -> Result<T, String> {
        text.trim()
            .parse::<T>()
            .map_err(|_| format!("`{text}` is not a number"))
    }

    fn f64_where(text: &str, ok: impl Fn(f64) -> bool, range: &str) -> Result<f64, String> {
        let v: f64 = number(text)?;
        if v.is_finite() && ok(v) {
            Ok(v)
        } else {
            Err(format!("{text} is not in {range}"))
        }
    }

    /// A finite number.
    pub fn finite(text: &str) -> Result<f64, String> {
        f64_where(text, |_| true, "the finite numbers")
    }

    /// A finite number > 0.
    pub fn positive(text: &str) -> Result<f64, String> {
        f64_where(text, |v| v > 0.0, "(0, ∞)")
    }

    /// A finite number ≥ 0.
    pub fn non_negative(text: &str) -> Result<f64, String> {
        f64_where(text, |v| v >= 0.0, "[0, ∞)")
    }

    /// A finite f32 ≥ 0.
    pub fn non_negative_f32(text: &str) -> Result<f32, String> {
        let v: f32 = number(text)?;
        if v.is_finite() && v >= 0.0 {
            Ok(v)
        } else {
            Err(format!("{text} is not in [0, ∞)"))
        }
    }

    /// A number in [0, 1].
    pub fn unit_interval(text: &str) -> Result<f64, String> {
        f64_where(text, |v| (0.0..=1.0).contains(&v), "[0, 1]")
    }

    /// A learning rate in (0, 100] (refinement's).
    pub fn learning_rate(text: &str) -> Result<f64, String> {
        let max = crate::encode::refine::MAX_LEARNING_RATE;
        f64_where(text, |v| v > 0.0 && v <= max, &format!("(0, {max}]"))
    }

    /// A learning rate in [0, 100] (0: off).
    pub fn learning_rate_or_zero(text: &str) -> Result<f64, String> {
        let max = crate::encode::refine::MAX_LEARNING_RATE;
        f64_where(text, |v| (0.0..=max).contains(&v), &format!("[0, {max}]"))
    }

    /// A field of view in (0, 180) degrees.
    pub fn fov_degrees(text: &str) -> Result<f64, String> {
        f64_where(text, |v| v > 0.0 && v < 180.0, "(0, 180) degrees")
    }

    /// An elevation in (-90, 90) degrees.
    pub fn elevation_degrees(text: &str) -> Result<f64, String> {
        f64_where(text, |v| v.abs() < 90.0, "(-90, 90) degrees")
    }

    /// A whole number in `lo..=hi`.
    pub fn count_in(text: &str, lo: usize, hi: usize) -> Result<usize, String> {
        let v: usize = number(text)?;
        if (lo..=hi).contains(&v) {
            Ok(v)
        } else {
            Err(format!("{v} is not in {lo}..={hi}"))
        }
    }

    /// Foreground slots to encode: 0..=1024.
    pub fn encode_slots(text: &str) -> Result<usize, String> {
        count_in(text, 0, crate::model::config::MAX_ENCODE_SLOTS)
    }

    /// Encoding tries: 1..=100.
    pub fn encode_tries(text: &str) -> Result<usize, String> {
        count_in(text, 1, crate::model::config::MAX_ENCODE_TRIES)
    }

    /// At least one.
    pub fn at_least_one(text: &str) -> Result<usize, String> {
        count_in(text, 1, usize::MAX)
    }

    /// Frames of a camera path: 1..=100000.
    pub fn path_frames(text: &str) -> Result<usize, String> {
        count_in(text, 1, 100_000)
    }

    /// An image side: 1..=16384.
    pub fn image_side(text: &str) -> Result<u32, String> {
        count_in(text, 1, crate::camera::MAX_IMAGE_SIDE as usize).map(|v| v as u32)
    }

    /// Samples per ray: 1..=4096.
    pub fn samples(text: &str) -> Result<usize, String> {
        count_in(text, 1, 4096)
    }

    #[cfg(test)]
    mod tests {
        #[test]
        fn ranges_and_non_numbers() {
            assert_eq!(super::unit_interval("0.5"), Ok(0.5));
            for bad in ["2", "-0.1", "nan", "inf", "x"] {
                assert!(super::unit_interval(bad).is_err(), "{bad}");
            }
            assert!(super::learning_rate("1e38").is_err());
            assert!(super::learning_rate("0").is_err());
            assert_eq!(super::learning_rate_or_zero("0"), Ok(0.0));
            assert!(super::fov_degrees("180").is_err());
            assert!(super::encode_slots("1025").is_err());
            assert_eq!(super::encode_slots("0"), Ok(0));
            assert!(super::encode_tries("0").is_err());
            assert!(super::image_side("0").is_err());
            assert!(super::image_side("16385").is_err());
            assert!(super::non_negative_f32("nan").is_err());
        }
    }
}

/// Every stage's clap command, by binary name: the man pages are generated from this list.
pub fn commands() -> Vec<clap::Command> {
    use clap::CommandFactory;
    vec![
        encode::EncodeArgs::command(),
        edit::EditArgs::command(),
        render::RenderArgs::command(),
        cameras::CamerasArgs::command(),
        eval::EvalArgs::command(),
        synth::SynthArgs::command(),
        train::TrainArgs::command(),
        sheet::SheetArgs::command(),
    ]
}

/// How an encoding is fitted to its input image, shared by `colf-encode` and `colf-eval --data`.
/// Unset flags take the model's measured defaults (its config's `inference`, see
/// `colf-train configure`), or one encoder pass for a model without them.
#[derive(clap::Args, Debug, Clone)]
pub struct FitArgs {
    /// One encoder pass: the model's training slot count, one try, no refinement (the fastest
    /// encoding; --slots still chooses K).
    #[arg(long, conflicts_with_all = ["tries", "refine"])]
    pub fast: bool,

    /// Encode N times (slot noise seeds S, S+1, ...) and keep the encoding that reconstructs the
    /// input image best (default: the model's).
    #[arg(long, value_name = "N", value_parser = parse::encode_tries)]
    pub tries: Option<usize>,

    /// Refine the slot latents with N Adam steps on the input image (0: the encoder's latents;
    /// default: the model's).
    #[arg(long, value_name = "N")]
    pub refine: Option<usize>,

    /// Learning rate of the refinement on the slot latents (default: the model's, else 0.01).
    #[arg(long, value_name = "LR", allow_negative_numbers = true, value_parser = parse::learning_rate)]
    pub refine_lr: Option<f64>,

    /// Pixels of the input image rendered per refinement step (all when the image has fewer;
    /// default: the model's, else 1,024; 512 makes the bundled model's default encoding 1.7x
    /// faster for -0.05 dB on novel views, docs/speed.md).
    #[arg(long, value_name = "R", value_parser = parse::at_least_one)]
    pub refine_rays: Option<usize>,

    /// With several input views: up to N slots added where the views agree on something the
    /// refined slots do not draw (blobs of the renders' residual whose centre rays meet), then
    /// all refined again and dropped unless needed, and the whole step undone if the views are
    /// then drawn worse (0: none; default: 3, 0 with --fast; docs/eval.md).
    #[arg(long, value_name = "N")]
    pub agreed_slots: Option<usize>,

    /// With three input views or more: before each later view's slots are matched with those
    /// kept so far, refine the kept slots N steps on the views already taken, so that they sit
    /// where those views agree rather than at one view's guess of their depth (0: none; default:
    /// the one-view refinement's steps, 0 with --fast; docs/eval.md).
    #[arg(long, value_name = "N")]
    pub triangulate: Option<usize>,

    /// Pull toward the encoder's latents during refinement: W * mean((z - z0)^2).
    #[arg(long, default_value_t = crate::encode::refine::RefineOptions::default().anchor_weight, value_name = "W", allow_negative_numbers = true, value_parser = parse::non_negative)]
    pub refine_anchor: f64,

    /// Drop slots the input image does not need (smallest attention mass first) while its
    /// render's mean squared error grows by at most MSE in all: an object drawn by two slots
    /// keeps one, so edits move or delete all of it (0: keep every slot; default: 2e-5, or 0
    /// with --fast).
    #[arg(long, value_name = "MSE", value_parser = parse::unit_interval)]
    pub redundant: Option<f64>,

    /// Also move the slots' frame origins during refinement, with this learning rate (world
    /// units; 0: frames fixed; default: the model's, else 0.003).
    #[arg(long, value_name = "LR", allow_negative_numbers = true, value_parser = parse::learning_rate_or_zero)]
    pub refine_frame_lr: Option<f64>,

    /// During refinement, evaluate a slot only on the pixels near where its compositor weight
    /// or shadow exceeds EPS (checked every few steps on a coarse grid of the image; 0: every
    /// slot on every pixel, as before). Most slots matter on a small part of the image, so this
    /// is most of refinement's speed.
    #[arg(long, default_value_t = crate::encode::refine::DEFAULT_SUPPORT, value_name = "EPS", value_parser = parse::unit_interval)]
    pub refine_support: f64,

    /// While encoding (refinement; with one input image also judging the tries and the
    /// redundant slots), a slot casts no shadow on pixels whose shadow line passes farther than
    /// D world units from it (for a model with shadows along the light and no reach of its own;
    /// 0: every line). Far lines carry almost no shadow: in refinement the default saves 18 % of
    /// the default encoding's time for -0.003 dB on held-out scenes; the codes are rendered with
    /// the model's own shadows (docs/speed.md).
    #[arg(long, default_value_t = crate::encode::refine::DEFAULT_REFINE_SHADOW_REACH, value_name = "D", allow_negative_numbers = true, value_parser = parse::non_negative)]
    pub refine_shadow_reach: f64,

    /// While encoding (refinement; with one input image also judging the tries and the
    /// redundant slots), a slot is left out of the pixels whose ray passes farther than D units
    /// from its frame origin (for a light-field model with no `slot_reach` of its own; 0: every
    /// slot on every pixel). Slots draw near their frames, and most light-field evaluations are
    /// far ones: the default takes 1.8–2.1× less CPU time in the default encoding for +0.007 dB on
    /// held-out scenes; the codes are rendered with all of the model's slots (docs/speed.md).
    #[arg(long, default_value_t = crate::encode::refine::DEFAULT_REFINE_SLOT_REACH, value_name = "D", allow_negative_numbers = true, value_parser = parse::non_negative)]
    pub refine_slot_reach: f64,

    /// For a model with a static background (a city model): during refinement, also the
    /// compositor's mask loss against each input view's object proposals (the pixels the
    /// background's render does not explain), weighted W, objects matched to slots view by view
    /// as in training; the colour loss alone lets the background keep the object pixels that
    /// look like it (default: the model's, else 0: colour alone).
    #[arg(long, value_name = "W", allow_negative_numbers = true, value_parser = parse::non_negative)]
    pub refine_mask: Option<f64>,

    /// With --refine-mask: proposal pixels left unsure within PX pixels of an object count to
    /// it (default: the model's, else 0).
    #[arg(long, value_name = "PX")]
    pub refine_mask_claim: Option<usize>,

    /// With --refine-mask: match each view's objects to slots and ask each object of its own
    /// slot, as training does (default: an object's pixels ask only that some slot draw them,
    /// and the colour loss says which).
    #[arg(long)]
    pub refine_mask_match: bool,
}

impl FitArgs {
    /// The encoding to run with `model_config`: `slots` (the stage's --slots) and these flags
    /// where given, else `--fast`'s one pass, else the model's defaults.
    pub fn encoding(
        &self,
        model_config: &crate::model::Config,
        slots: Option<usize>,
    ) -> crate::model::config::InferenceConfig {
        let base = if self.fast {
            crate::model::config::InferenceConfig::one_pass(model_config.default_slots)
        } else {
            model_config.default_inference()
        };
        crate::model::config::InferenceConfig {
            slots: slots.unwrap_or(base.slots),
            tries: self.tries.unwrap_or(base.tries),
            refine: self.refine.unwrap_or(base.refine),
            refine_lr: self.refine_lr.or(base.refine_lr),
            refine_frame_lr: self.refine_frame_lr.or(base.refine_frame_lr),
            refine_rays: self.refine_rays.or(base.refine_rays),
            refine_mask: self.refine_mask.or(base.refine_mask),
            refine_mask_claim: self.refine_mask_claim.or(base.refine_mask_claim),
        }
    }

    /// [`FitArgs::encoding`] for an encoding of `views` views of one scene: unless --refine
    /// says otherwise, several views refine [`crate::encode::multiview::MULTI_VIEW_REFINE_FACTOR`]
    /// times the model's steps.
    pub fn encoding_for_views(
        &self,
        model_config: &crate::model::Config,
        slots: Option<usize>,
        views: usize,
    ) -> crate::model::config::InferenceConfig {
        let mut encoding = self.encoding(model_config, slots);
        if views > 1 && self.refine.is_none() {
            encoding.refine *= crate::encode::multiview::MULTI_VIEW_REFINE_FACTOR;
        }
        encoding
    }

    /// The error budget for dropping redundant slots: --redundant, else none for `--fast` (one
    /// pass, nothing more), else `DEFAULT_REDUNDANT_MSE`.
    pub fn redundant_mse(&self) -> f64 {
        self.redundant.unwrap_or(if self.fast {
            0.0
        } else {
            crate::encode::DEFAULT_REDUNDANT_MSE
        })
    }

    /// How many slots several views may add where they agree: --agreed-slots, else none for
    /// `--fast` (an added slot needs the refinement it skips), else `DEFAULT_AGREED_SLOTS`.
    pub fn agreed_slots(&self) -> usize {
        self.agreed_slots.unwrap_or(if self.fast {
            0
        } else {
            crate::encode::residual::DEFAULT_AGREED_SLOTS
        })
    }

    /// Steps of the triangulation before each later view's slots are matched: --triangulate,
    /// else the one-view encoding's refinement steps (none with --fast, which refines nothing).
    pub fn triangulate_steps(
        &self,
        model_config: &crate::model::Config,
        slots: Option<usize>,
    ) -> usize {
        self.triangulate
            .unwrap_or_else(|| self.encoding(model_config, slots).refine)
    }

    /// The encoding these flags ask for with `model_config`, `slots` (the stage's --slots) and
    /// slot-noise `seed` (no camera or source: the stage sets them per image).
    pub fn encode_options(
        &self,
        model_config: &crate::model::Config,
        slots: Option<usize>,
        seed: u64,
    ) -> crate::encode::EncodeOptions {
        self.encode_options_for_views(model_config, slots, seed, 1)
    }

    /// [`FitArgs::encode_options`] for an encoding of `views` views of one scene (see
    /// [`FitArgs::encoding_for_views`]).
    pub fn encode_options_for_views(
        &self,
        model_config: &crate::model::Config,
        slots: Option<usize>,
        seed: u64,
        views: usize,
    ) -> crate::encode::EncodeOptions {
        let encoding = self.encoding_for_views(model_config, slots, views);
        crate::encode::EncodeOptions {
            num_slots: encoding.slots,
            seed,
            tries: encoding.tries,
            refine: self.options(&encoding, seed),
            redundant_mse: self.redundant_mse(),
            agreed_slots: self.agreed_slots(),
            triangulate_steps: self.triangulate_steps(model_config, slots),
            ..crate::encode::EncodeOptions::one_pass(encoding.slots)
        }
    }

    /// The refinement options of `encoding` (its steps and learning rates, the other settings
    /// from these flags); the pixel subsets are drawn from `seed`.
    pub fn options(
        &self,
        encoding: &crate::model::config::InferenceConfig,
        seed: u64,
    ) -> crate::encode::refine::RefineOptions {
        let defaults = crate::encode::refine::RefineOptions::default();
        crate::encode::refine::RefineOptions {
            steps: encoding.refine,
            lr: encoding.refine_lr.unwrap_or(defaults.lr),
            rays: encoding.refine_rays.unwrap_or(defaults.rays),
            anchor_weight: self.refine_anchor,
            frame_lr: encoding.refine_frame_lr.unwrap_or(defaults.frame_lr),
            support: self.refine_support,
            shadow_reach: self.refine_shadow_reach,
            slot_reach: self.refine_slot_reach,
            mask_weight: encoding.refine_mask.unwrap_or(defaults.mask_weight),
            mask_claim: encoding.refine_mask_claim.unwrap_or(defaults.mask_claim),
            mask_match: self.refine_mask_match,
            seed,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::encode::EncodeArgs;
    use crate::encode::multiview::MULTI_VIEW_REFINE_FACTOR;
    use crate::model::config::InferenceConfig;
    use crate::model::Config;
    use clap::Parser;

    fn encoding(cfg: &Config, flags: &[&str]) -> InferenceConfig {
        let args = EncodeArgs::try_parse_from([&["colf-encode", "x.png"], flags].concat()).unwrap();
        args.fit.encoding(cfg, args.slots)
    }

    #[test]
    fn several_views_refine_longer_unless_told() {
        let tuned = Config {
            inference: Some(InferenceConfig {
                slots: 12,
                tries: 4,
                refine: 50,
                refine_lr: None,
                refine_frame_lr: None,
                refine_rays: None,
                refine_mask: None,
                refine_mask_claim: None,
            }),
            ..Config::small()
        };
        let for_views = |flags: &[&str], views: usize| {
            let args =
                EncodeArgs::try_parse_from([&["colf-encode", "x.png"], flags].concat()).unwrap();
            args.fit
                .encoding_for_views(&tuned, args.slots, views)
                .refine
        };
        assert_eq!(for_views(&[], 1), 50);
        assert_eq!(for_views(&[], 3), 50 * MULTI_VIEW_REFINE_FACTOR);
        assert_eq!(for_views(&["--refine", "30"], 3), 30);
        assert_eq!(for_views(&["--fast"], 3), 0);
        // The kept slots are triangulated for as long as one view is refined.
        let triangulate = |flags: &[&str]| {
            let args =
                EncodeArgs::try_parse_from([&["colf-encode", "x.png"], flags].concat()).unwrap();
            args.fit
                .encode_options_for_views(&tuned, args.slots, 0, 3)
                .triangulate_steps
        };
        assert_eq!(triangulate(&[]), 50);
        assert_eq!(triangulate(&["--refine", "30"]), 30);
        assert_eq!(triangulate(&["--triangulate", "7"]), 7);
        assert_eq!(triangulate(&["--fast"]), 0);
    }

    #[test]
    fn unset_flags_take_the_models_encoding_and_fast_is_one_pass() {
        let plain = Config::small();
        let measured = InferenceConfig {
            slots: 12,
            tries: 4,
            refine: 50,
            refine_lr: None,
            refine_frame_lr: None,
            refine_rays: None,
            refine_mask: None,
            refine_mask_claim: None,
        };
        let tuned = Config {
            inference: Some(measured),
            ..Config::small()
        };
        assert_eq!(encoding(&plain, &[]), InferenceConfig::one_pass(7));
        assert_eq!(encoding(&tuned, &[]), measured);
        assert_eq!(encoding(&tuned, &["--fast"]), InferenceConfig::one_pass(7));
        assert_eq!(
            encoding(&tuned, &["--fast", "--slots", "9"]),
            InferenceConfig::one_pass(9)
        );
        assert_eq!(
            encoding(&tuned, &["--refine", "0", "--slots", "8"]),
            InferenceConfig {
                slots: 8,
                tries: 4,
                refine: 0,
                refine_lr: None,
                refine_frame_lr: None,
                refine_rays: None,
                refine_mask: None,
                refine_mask_claim: None,
            }
        );
        assert_eq!(
            encoding(&plain, &["--tries", "3"]),
            InferenceConfig {
                slots: 7,
                tries: 3,
                refine: 0,
                refine_lr: None,
                refine_frame_lr: None,
                refine_rays: None,
                refine_mask: None,
                refine_mask_claim: None,
            }
        );
        // A model's measured learning rates reach the refinement unless a flag says otherwise;
        // a model without them refines at the flags' defaults.
        let rated = Config {
            inference: Some(InferenceConfig {
                refine: 25,
                refine_lr: Some(0.02),
                refine_frame_lr: Some(0.015),
                refine_rays: Some(512),
                refine_mask: None,
                refine_mask_claim: None,
                ..measured
            }),
            ..Config::small()
        };
        let rates = |cfg: &Config, flags: &[&str]| {
            let args =
                EncodeArgs::try_parse_from([&["colf-encode", "x.png"], flags].concat()).unwrap();
            let opts = args.fit.options(&args.fit.encoding(cfg, args.slots), 0);
            (opts.steps, opts.lr, opts.frame_lr, opts.rays)
        };
        assert_eq!(rates(&rated, &[]), (25, 0.02, 0.015, 512));
        assert_eq!(
            rates(&rated, &["--refine-lr", "0.05", "--refine-rays", "2048"]),
            (25, 0.05, 0.015, 2048)
        );
        assert_eq!(
            rates(&rated, &["--refine-frame-lr", "0"]),
            (25, 0.02, 0.0, 512)
        );
        assert_eq!(rates(&tuned, &[]), (50, 0.01, 0.003, 1024));
        // --fast with --tries or --refine is a usage error.
        for flags in [["--fast", "--tries", "2"], ["--fast", "--refine", "2"]] {
            let err = EncodeArgs::try_parse_from([&["colf-encode", "x.png"], &flags[..]].concat())
                .unwrap_err();
            assert_eq!(err.exit_code(), 2);
        }
    }

    #[test]
    fn redundant_slots_are_dropped_unless_fast_or_told() {
        let budget = |flags: &[&str]| {
            EncodeArgs::try_parse_from([&["colf-encode", "x.png"], flags].concat())
                .unwrap()
                .fit
                .redundant_mse()
        };
        assert_eq!(budget(&[]), crate::encode::DEFAULT_REDUNDANT_MSE);
        assert_eq!(budget(&["--fast"]), 0.0);
        assert_eq!(budget(&["--fast", "--redundant", "1e-5"]), 1e-5);
        assert_eq!(budget(&["--redundant", "0"]), 0.0);
    }
}
