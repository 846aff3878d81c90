//! The COLF model in candle: encoder → background-aware slot attention → per-slot hypernetwork
//! light fields → colour/ordering heads → compositor. See `docs/model.md` for the tensor names,
//! the checkpoint format and the design choices.
//!
//! Two levels:
//! - [`ColfNet`] (`net.rs`): the module tree on tensors (differentiable; used by training).
//! - [`Colf`] (`host.rs`): a loaded model with the host-side API that `colf-encode`/`colf-render` use:
//!   [`Colf::encode`] an image into slot latents, [`Colf::prepare`] slots (hypernetworks run
//!   once per slot) and [`Colf::render_rays`] any number of world rays in bounded-memory chunks.

pub mod background_reader;
pub mod checkpoint;
pub mod compositor;
pub mod config;
pub mod conv;
pub mod decode_kernel;
pub mod encoder;
pub mod frames;
pub mod fused;
pub mod grow;
pub mod heads;
pub mod history;
mod host;
pub mod hypernet;
pub mod init;
pub mod layers;
pub mod light_field;
mod net;
pub mod rays;
pub mod slot_attention;
pub mod volumetric;

pub use config::Config;
pub use history::TrainingRun;
pub use host::{Colf, Encoded, PreparedSlots, RayOutput};
pub use light_field::SlotWeights;
pub use net::{ColfNet, Decoded, Decoder, LightFieldDecoder};
pub use rays::{FrameDerivatives, HostRays, RayBatch, SceneRays};
pub use slot_attention::SlotOutput;
