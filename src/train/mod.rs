//! Training: optimizer with checkpointable state, and (as it lands) the training loop.

pub mod adam;
pub mod average;
pub mod batch;
pub mod plot;
pub mod trainer;
