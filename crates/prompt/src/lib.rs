//! Prompt and history segment sampling (`promptdt-reference.md` b), pure and seeded.
//!
//! - [`config`]: [`SamplerConfig`] and its options (prompt position, ranking, normalisation scope).
//! - [`normalize`]: global state statistics ([`StateNorm`]).
//! - [`ranking`]: the reference's trajectory ranking and sampling weights.
//! - [`segment`]: one segment (history or prompt) cut from a trajectory, padded and normalised.
//! - [`batch`]: [`BatchSampler`]: the multi-task batch of M samples per task, and evaluation prompts.
//!
//! Output is host memory ([`SegmentBatch`], [`PromptDtBatch`]); the model crate moves it to a device.

pub mod batch;
pub mod config;
pub mod normalize;
pub mod ranking;
pub mod segment;

pub use batch::{BatchSampler, PromptDtBatch, SegmentBatch};
pub use config::{
    NormalizationScope, PromptPosition, SamplerConfig, SamplerError, TrajectoryRanking,
};
pub use normalize::StateNorm;

/// The RNG every sampler takes. ChaCha8 is portable and reproducible across platforms and versions.
pub type Rng = rand_chacha::ChaCha8Rng;
