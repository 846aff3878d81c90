//! `colf-encode`: one image, or several views of one scene → object slots (a codes file).

use clap::Parser;

/// Encode one image, or several views of one scene, into object slots.
#[derive(Parser, Debug)]
#[command(
    name = "colf-encode",
    version,
    about = "Encode one image, or several views of one scene, into object slots (a colf codes file)",
    long_about = "Find the objects in one image without labels: the encoder and background-aware \
slot attention of the model turn IMAGE into K foreground slot latents and one background latent, \
written as a codes file (safetensors; see colf-edit(1) and the README for its contract).\n\n\
The image (PNG; `-` for stdin) is resized to the model's encoder input. An image of more than \
1048576 pixels (1024²) is first reduced to that input size on its 8/16-bit pixels, and \
refinement then fits the reduced image; PNG inputs may hold at most 67108864 pixels (8192²) \
and 512 MiB of decoded pixels, checked from the header before decoding. With \
--camera, every slot's slot_to_world is set to that frame's camera-to-world, so slots live in \
world space and can be moved and merged with slots of other scenes; without it the identity is \
used (the camera frame of the image is the world). --slots sets the number of foreground slots \
(any K >= 0; default: the model's). --prune drops slots that took less than MASS of the \
attention, so a scene keeps only the slots it needs. The slot noise is drawn from a seeded \
generator: the same input, model, options and --seed give byte-identical output.\n\n\
--refine N then takes N Adam steps on the slot latents and the slot frames' origins (the \
model's weights fixed; --refine-frame-lr 0 keeps the frames) to lower the colour error of IMAGE \
as seen by its camera: the encoder's latents are a one-pass guess for any scene, and a few steps \
fit this one. Only IMAGE is used, so novel views stay predictions. Too many steps or too high a \
--refine-lr fit the input view at the expense of novel views. --tries N encodes N times (slot \
noise seeds --seed, --seed + 1, ...) and keeps the encoding whose render of IMAGE is closest to \
it, before any refinement.\n\n\
Last, slots IMAGE does not need are dropped: smallest attention mass first, a slot goes when \
the slots left still render IMAGE with a mean squared error at most --redundant MSE above that \
of them all (the bound is on the total). Given more slots than objects, slot attention \
sometimes gives one object two slots that draw it alike; keeping one means an edit that moves \
or deletes it moves or deletes all of it. --redundant 0 keeps every slot.\n\n\
Unset, --slots, --tries, --refine, --refine-lr and --refine-frame-lr take the model's default \
encoding (its config's `inference`, written by colf-train configure; a model without one is encoded in one pass with \
its training slot count). The bundled default model's is 12 slots, 4 tries and 20 refinement \
steps of 512 rays, chosen within a CPU budget (about 2.9 s of CPU a 128² image); the \
supervised and blender models' is 12 slots, 4 tries and 50 steps of 1,024 rays \
(docs/refinement.md). \
--fast is the one-pass encoding (the model's training slot count, about 0.03 s an image), for \
when speed matters more.\n\n\
Several images of one scene (IMAGE... with --camera, image i seen by --frame's i-th frame, \
by default frame i) are encoded into one scene: each view is encoded as above (tries, and the \
slots its own view does not need dropped), then slots of different views that draw the same \
object are matched into one — from the third view on, the slots kept so far are first refined \
on the views before it (--triangulate steps), so that they sit where those views agree; each view's \
slots are rendered into the views before it, and two \
slots whose label maps overlap (intersection over union at least 0.2 over those views) are one \
object, as is a slot whose pixels lie mostly (60 %) inside one earlier slot's in every view (a \
piece of an object a view split); the earlier view's slot stays — so an object seen in several views gets one slot and \
an object only one view sees keeps its own; the background is the first view's. The kept slots \
are then refined on all views at once (--refine-rays is per view; unless --refine says \
otherwise, twice the model's default steps); up to three slots are then added where the views \
agree on something no slot draws, refined with the rest and kept only where two views need them \
(--agreed-slots; the step is undone if it draws the views worse), and the slots no view needs \
dropped (--redundant on the mean error over the views). Each slot's source names the image it \
came from (`agreed#N` for an added slot). One image gives exactly the codes it always did.\n\n\
The model is --model, else $COLF_MODEL, else the default model bundled with colf.",
    after_help = "Examples:\n  colf-encode view_000.png --camera transforms.json -o scene.codes\n  \
colf-encode photo.png --slots 10 --prune 0.02 -o - | colf-edit --inspect\n  \
colf-encode view_000.png --camera transforms.json --fast -o scene.codes\n  \
colf-encode view_000.png view_001.png view_002.png --camera transforms.json -o scene.codes"
)]
pub struct EncodeArgs {
    /// Input image, PNG (`-`: stdin); several: views of one scene (needs --camera).
    #[arg(value_name = "IMAGE", required = true, num_args = 1..)]
    pub images: Vec<String>,

    /// transforms.json holding the camera of each IMAGE (sets slot_to_world).
    #[arg(long, value_name = "CAMERAS.json")]
    pub camera: Option<String>,

    /// Which frames of --camera are the IMAGEs' cameras, one per image (default: 0, 1, ...).
    #[arg(long, value_name = "N", num_args = 1.., value_delimiter = ',', requires = "camera")]
    pub frame: Vec<usize>,

    /// Number of foreground slots (default: the model's).
    #[arg(long, value_name = "K", value_parser = crate::cli::parse::encode_slots)]
    pub slots: Option<usize>,

    /// Drop slots whose attention mass is below MASS (in [0, 1]).
    #[arg(long, value_name = "MASS", value_parser = crate::cli::parse::unit_interval)]
    pub prune: Option<f64>,

    /// Seed of the slot noise.
    #[arg(long, default_value_t = 0, value_name = "S")]
    pub seed: u64,

    #[command(flatten)]
    pub fit: crate::cli::FitArgs,

    /// Model file, or a bundled model's name (`default`, `supervised`, `blender`); default: $COLF_MODEL, else
    /// the bundled default model.
    #[arg(long, value_name = "M")]
    pub model: Option<String>,

    /// Name recorded as each slot's source (default: the image's file name).
    #[arg(long, value_name = "NAME")]
    pub source: Option<String>,

    /// Where to write the codes (`-`: stdout, the default; refused on a terminal).
    #[arg(short, long, default_value = "-", value_name = "OUT")]
    pub output: String,
}

/// Runs `colf-encode`.
pub fn run(args: &EncodeArgs) -> anyhow::Result<()> {
    use crate::camera::Cameras;
    use crate::cli::UsageError;
    use crate::encode::multiview::{encode_views, ViewInput};
    use crate::encode::{encode_image, EncodeOptions};
    use anyhow::bail;
    let stdin = args.images.iter().filter(|i| *i == "-").count();
    if stdin > 1 {
        return Err(UsageError("more than one IMAGE is stdin (`-`)".into()).into());
    }
    if stdin == 1 && args.camera.as_deref() == Some("-") {
        return Err(crate::cli::both_stdin("IMAGE", "--camera"));
    }
    let several = args.images.len() > 1;
    if several && args.camera.is_none() {
        return Err(UsageError(
            "several IMAGEs need --camera: their cameras place the slots in one world".into(),
        )
        .into());
    }
    let frames: Vec<usize> = if args.frame.is_empty() {
        (0..args.images.len()).collect()
    } else {
        args.frame.clone()
    };
    if frames.len() != args.images.len() {
        return Err(UsageError(format!(
            "{} IMAGEs but {} --frame values: give one frame per image",
            args.images.len(),
            frames.len()
        ))
        .into());
    }
    let model = crate::cli::model_path::load_model(args.model.as_deref())?;
    let images = args
        .images
        .iter()
        .map(|path| {
            crate::image_io::decode_rgb_for_encoder(
                &crate::io::read_input(path, true)?,
                crate::io::display_name(path),
                model.config().encoder_size as u32,
                crate::image_io::ENCODE_FULL_RES_PIXELS,
            )
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let cameras = match &args.camera {
        None => None,
        Some(path) => {
            let cameras = Cameras::read(path)?;
            let picked = frames
                .iter()
                .map(|&frame| match cameras.frames.get(frame) {
                    Some(f) => Ok(f.clone()),
                    None => bail!(
                        "{}: --frame {frame} does not exist (the file has {} frames)",
                        crate::io::display_name(path),
                        cameras.frames.len()
                    ),
                })
                .collect::<anyhow::Result<Vec<_>>>()?;
            Some(picked)
        }
    };
    let file_name = |path: &str| {
        std::path::Path::new(path)
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .filter(|_| path != "-")
            .unwrap_or_else(|| "stdin".into())
    };
    let source = |i: usize| match &args.source {
        Some(name) if several => format!("{name}/view{i}"),
        Some(name) => name.clone(),
        None => file_name(&args.images[i]),
    };
    let opts = EncodeOptions {
        prune_mass: args.prune,
        ..args.fit.encode_options_for_views(
            model.config(),
            args.slots,
            args.seed,
            args.images.len(),
        )
    };
    let codes = match cameras {
        Some(cameras) if several => {
            let views: Vec<ViewInput> = images
                .iter()
                .zip(cameras)
                .enumerate()
                .map(|(i, (image, camera))| ViewInput {
                    image,
                    camera,
                    source: source(i),
                })
                .collect();
            encode_views(&model, &views, &opts)?.0
        }
        cameras => {
            let opts = EncodeOptions {
                camera: cameras.and_then(|c| c.into_iter().next()),
                source: source(0),
                ..opts
            };
            encode_image(&model, &images[0], &opts)?
        }
    };
    codes.write(&args.output)
}
