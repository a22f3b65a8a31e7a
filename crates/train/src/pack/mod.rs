//! A pack: N independent runs of one environment family trained in lockstep in one process on one
//! device (issue 30). Each run keeps its own seed streams, sampler, weights, optimiser state,
//! clipping, schedule, evaluation and run directory; only the gradient steps are shared, by a
//! [`PackEngine`] that steps every run of the pack at once.

pub mod batched;
pub mod engine;

pub use batched::{BatchedEngine, PackLayout};
pub use engine::{PackEngine, SlotSpec, SlotState, SlotStep};
