//! Rendering: slot codes + cameras → frames (colour, masks, depth order).
//!
//! Who calls what:
//! - [`scene`]: [`PreparedScene`] is the entry point of `colf-render`, `colf-eval` and the
//!   examples. It checks that the codes were encoded by the model in use, runs the
//!   hypernetworks once per slot, and renders each frame exactly or adaptively.
//! - [`fast`]: [`fast::FastRenderer`], the inference path: the slots' light fields evaluated
//!   with plain `gemm` on host memory, the same weights and results as the candle path (tested
//!   to 1e-4 in `tests/render_fast.rs`). Encoding also uses it to judge redundant slots.
//! - [`adaptive`]: renders a coarse frame first and evaluates each slot only where it can
//!   matter (`--adaptive ε`).
//! - [`output`]: [`output::FrameRender`], a rendered frame and how it is written (PNG, EXR,
//!   masks), read back by tests.

pub mod adaptive;
pub mod fast;
pub mod output;
pub mod scene;

pub use scene::{parse_frame_range, FrameSelection, PreparedScene, RenderOptions};
