//! colf — Compositional Object Light Fields.
//!
//! One photo of a scene → a set of object slots, each a small latent code conditioning its own
//! neural light field; slots are edited as data and rendered from any camera with a single
//! network evaluation per ray per object (a second one along the light where objects cast
//! shadows). See `README.md` and `../shared/DESIGN.md`.
//!
//! The modules each do one job:
//! - [`io`]: stdin/stdout, atomic output files, terminal refusal.
//! - [`cli`]: command-line definitions of every stage (man pages are generated from them).
//! - [`camera`]: `transforms.json` and uORF cameras, rays, Plücker coordinates.
//! - [`camera_path`]: orbits and dollies for novel-view renders.
//! - [`codes`]: the slot codes safetensors file.
//! - [`edit`]: the JSON edit language of `colf-edit`.
//! - [`image_io`]: PNG reading (RGB in [0, 1], mask labels) and deterministic PNG writing.
//! - [`metrics`]: PSNR, SSIM, ARI, FG-ARI exactly as uORF / scikit-image / scikit-learn.
//! - [`tensorfile`]: deterministic safetensors writing, checked reading.

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
pub mod render;
pub mod sheet;
pub mod synth;
pub mod tensorfile;
pub mod train;
