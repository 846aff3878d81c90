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
by their ordering values.\n\n\
Outputs, for a frame whose file_path stem is S (else frame_NNNN, NNNN = the frame index):\n\n\
  DIR/S.png        8-bit sRGB RGB\n\n\
  DIR/S.mask.png   with --masks: 8-bit grey, 0 = background, k + 1 = slot k (argmax of the \
compositor weights)\n\n\
  DIR/S.exr        with --exr: float channels R, G, B; bg.weight and bg.order for the \
background; slotK.weight and slotK.order for slot K (compositor weight in [0, 1] and the \
world-comparable ordering value)\n\n\
Every file is written atomically. Codes encoded by another model are refused. The hypernetwork \
runs once per slot per run; rays are evaluated in chunks so memory stays bounded whatever the \
image size or slot count. --frames A..B renders a subset (half-open, like Rust ranges: 0..10 \
is frames 0 to 9; A.. and ..B work too) so batches can be split across processes.\n\n\
The model is --model, else $COLF_MODEL, else the small default model bundled with colf.",
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
    #[arg(long, value_name = "DIR")]
    pub out: String,

    /// Also write DIR/S.mask.png segmentation masks.
    #[arg(long)]
    pub masks: bool,

    /// Also write DIR/S.exr with float RGB and per-slot weight and ordering channels.
    #[arg(long)]
    pub exr: bool,

    /// Render only frames A..B (half-open; `A..`, `..B`, or a single index N).
    #[arg(long, value_name = "A..B")]
    pub frames: Option<String>,

    /// Rays evaluated per chunk (bounds memory).
    #[arg(long, default_value_t = 4096, value_name = "N")]
    pub chunk: usize,

    /// Model file (default: $COLF_MODEL, else the bundled default model).
    #[arg(long, value_name = "M")]
    pub model: Option<String>,
}
