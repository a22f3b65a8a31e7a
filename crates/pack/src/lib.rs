//! A pack: N independent runs of one environment family trained together in one process on one
//! device (`docs/packs.md`). Each run keeps its own seed streams, sampler, weights, optimiser state,
//! clipping, schedule, evaluation and run directory; only the gradient steps are shared, by a
//! [`PackEngine`] that steps every run of the pack at once. A crate above `pdt-train`, whose
//! learners it speaks to through `pdt_train::methods::Steppable` only: a run of a pack is its
//! method's own learner with its gradient steps taken here.
//!
//! - `model`: [`model::PackedPromptDt`], N Prompt-DT models of one shape as one (stacked weights,
//!   batched products): the batched engine's model.
//! - `engine`: the contract between the runs and an engine.
//! - `solo`: [`SoloEngine`], the exact engine (each run's solo step, one run after another): the
//!   CPU's engine and the batched engine's test oracle.
//! - `batched`: [`BatchedEngine`], every run's step as one batched computation (the GPU's).
//! - `hub`: where the runs' threads meet for each gradient step.
//! - `member`: a run of the pack as the run loop's `Learner` (its method's learner for all but the
//!   step).
//! - `run`: [`train_pack`], the pack checked, its data loaded once, its runs' loops in threads.
//! - `dir`: a pack directory (its `pack.json`, `pdt_rundir::pack::PackRecord`, and the runs'
//!   directories): [`train_pack_dir`], [`resume_pack_dir`].

// Errors carry the offending path, shape or tensor name (`pdt_train::run::RunError`), so they are
// large; they are returned on the cold path only (a failed run).
#![allow(clippy::result_large_err)]

pub mod batched;
mod dir;
pub mod engine;
mod hub;
mod member;
pub mod model;
mod run;
pub mod solo;

pub use batched::{BatchedEngine, PackLayout};
pub use dir::{resume_pack_dir, train_pack_dir};
pub use engine::{PackEngine, SlotSpec, SlotStep};
pub use run::{train_pack, PackOptions, PackRun};
pub use solo::SoloEngine;
