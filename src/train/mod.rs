//! Training: batches of rays from multi-view scenes, the training loop with checkpoints, model
//! averaging, and plots of training logs. The optimiser lives in [`crate::optim`] (encoding
//! refines latents with it too).

pub mod average;
pub mod batch;
pub mod init;
pub mod known_background;
pub mod plot;
pub mod trainer;
