//! colf — Compositional Object Light Fields.
//!
//! One photo of a scene → a set of object slots, each a small latent code conditioning its own
//! neural light field; slots are edited as data and rendered from any camera with a single
//! network evaluation per ray per object (a second one along the light where objects cast
//! shadows). See `README.md`, `HACKING.md` (the architecture) and `docs/formats.md` (the file
//! contracts).
//!
//! The modules, in pipeline order; each does one job, and dependencies point down this list
//! (the command-line layer [`cli`] calls the library, never the reverse):
//! - [`cli`]: the stages' command-line definitions (man pages are generated from them), each
//!   stage's `run`, and which model a stage uses ([`cli::model_path`]).
//! - [`synth`]: synthetic scenes with ground truth (`colf-synth`).
//! - [`dataset`]: multi-view scenes on disk (colf and uORF layouts) for training and evaluation.
//! - [`proposals`]: object proposals from an image alone (no mask), for training without labels.
//! - [`train`]: training batches, the training loop with checkpoints, averaging, plots.
//! - [`encode`]: one image → slot codes (one pass, tries, refinement, redundant-slot drop).
//! - [`edit`]: the JSON edit language of `colf-edit`.
//! - [`render`]: codes + cameras → frames (the fast renderer, adaptive rendering, outputs).
//! - [`evaluate`], [`metrics`]: the uORF protocol on a dataset; PSNR, SSIM, ARI, FG-ARI.
//! - [`model`]: the network in candle ([`model::ColfNet`]) and the loaded model with its host
//!   API ([`model::Colf`]); [`optim`]: Adam with saveable state.
//! - [`camera`], [`camera_path`]: cameras, rays, Plücker coordinates; orbits and dollies.
//! - [`codes`], [`tensorfile`], [`image_io`], [`io`], [`sheet`]: the files — slot codes,
//!   checked safetensors, PNG, atomic outputs and stdin/stdout, contact sheets.
//! - [`alloc`]: the allocator settings of the binaries.

pub mod alloc;
pub mod camera;
pub mod camera_path;
pub mod cli;
pub mod codes;
pub mod dataset;
pub mod edit;
pub mod encode;
pub mod evaluate;
pub mod image_io;
pub mod io;
pub mod metrics;
pub mod model;
pub mod optim;
pub mod proposals;
pub mod render;
pub mod sheet;
pub mod synth;
pub mod tensorfile;
pub mod train;
