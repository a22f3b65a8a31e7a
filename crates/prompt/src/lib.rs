//! Prompt and history segment sampling (`promptdt-reference.md` b), pure and seeded.
//!
//! - [`config`]: [`SamplerConfig`] and its options (prompt position, ranking, normalisation scope).
//! - [`normalize`]: global state statistics ([`StateNorm`]).
//! - [`ranking`]: the reference's trajectory ranking and sampling weights.
//! - [`segment`]: one segment (history or prompt) cut from a trajectory, padded and normalised.
//! - [`strategy`], [`bandit`]: test-time prompt strategies ([`PromptStrategy`]).
//! - [`batch`]: [`BatchSampler`]: the multi-task batch of M samples per task, and evaluation prompts.
//!
//! Output is host memory ([`SegmentBatch`], [`PromptDtBatch`]); the model crate moves it to a device.

pub mod bandit;
pub mod batch;
pub mod config;
pub mod normalize;
pub mod ranking;
pub mod segment;
pub mod strategy;

pub use batch::{BatchSampler, PromptDtBatch, SegmentBatch};
pub use config::{
    NormalizationScope, PromptPosition, SamplerConfig, SamplerError, TrajectoryRanking,
};
pub use normalize::StateNorm;
pub use strategy::{
    BanditConfig, BanditRule, PromptPick, PromptStrategy, PromptStrategyKind, SegmentChoice,
    StrategyError,
};

/// The RNG every sampler takes. ChaCha8 is portable and reproducible across platforms and versions.
pub type Rng = rand_chacha::ChaCha8Rng;
