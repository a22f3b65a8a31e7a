//! A pack: N independent runs of one environment family trained together in one process on one
//! device (issue 30). Each run keeps its own seed streams, sampler, weights, optimiser state,
//! clipping, schedule, evaluation and run directory; only the gradient steps are shared, by a
//! [`PackEngine`] that steps every run of the pack at once (`docs/packs.md`).
//!
//! - `engine`: the contract between the runs and an engine.
//! - `solo`: [`SoloEngine`], the exact engine (each run's solo step, one run after another): the
//!   CPU's engine and the batched engine's test oracle.
//! - `batched`: [`BatchedEngine`], every run's step as one batched computation (the GPU's).
//! - `hub`: where the runs' threads meet for each gradient step.
//! - `member`: a run of the pack as the run loop's `Learner` (solo code for all but the step).
//! - `run`: [`train_pack`], the pack checked, its data loaded once, its runs' loops in threads.
//! - `dir`: a pack directory (its `pack.json`, `pdt_rundir::pack::PackRecord`, and the runs'
//!   directories): [`train_pack_dir`], [`resume_pack_dir`].

pub mod batched;
mod dir;
pub mod engine;
mod hub;
mod member;
mod run;
pub mod solo;

pub use batched::{BatchedEngine, PackLayout};
pub use dir::{resume_pack_dir, train_pack_dir};
pub use engine::{PackEngine, SlotSpec, SlotState, SlotStep};
pub use run::{train_pack, PackOptions, PackRun};
pub use solo::SoloEngine;
