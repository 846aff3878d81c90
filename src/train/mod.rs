//! Training: optimizer with checkpointable state, and (as it lands) the training loop.

pub mod adam;
pub mod batch;
pub mod trainer;
pub mod plot;
