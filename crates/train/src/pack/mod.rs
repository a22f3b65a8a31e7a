//! A pack: N independent runs of one environment family trained together in one process on one
//! device, where one run's small steps would leave it mostly idle. Each run keeps its own seed
//! streams, sampler, weights, optimiser state, clipping, schedule, evaluation and run directory;
//! only the gradient steps are shared, by a
//! [`PackEngine`] that steps every run of the pack at once (`docs/packs.md`).
//!
//! - `engine`: the contract between the runs and an engine.
//! - `solo`: [`SoloEngine`], the exact engine (each run's solo step: on the CPU each run on a thread
//!   of its own, its steps taken as the run hands them over; elsewhere in turn).
//! - `batched`: [`BatchedEngine`], every run's step as one batched computation.
//! - `hub`: where the runs' threads meet for each gradient step (or start their own, for an engine
//!   whose slots step alone), and, with an engine that acts for its runs, for each environment
//!   step's forward of their evaluations.
//! - `member`: a run of the pack as the run loop's `Learner` (solo code for all but the step).
//! - `run`: [`train_pack`], the pack checked, its data loaded once, its runs' loops in threads.
//! - `dir`: a pack directory (`pack.json` and the runs' directories): [`train_pack_dir`],
//!   [`resume_pack_dir`].

pub mod batched;
mod dir;
pub mod engine;
mod hub;
mod member;
mod run;
pub mod solo;

pub use batched::{BatchedEngine, PackLayout};
pub use dir::{is_pack_dir, resume_pack_dir, train_pack_dir, PackRecord, PackRecordRun, PACK_JSON};
pub use engine::{PackEngine, SlotAct, SlotSpec, SlotState, SlotStep};
pub use run::{train_pack, Engine, PackEval, PackOptions, PackRun};
pub use solo::{SoloEngine, SoloThreads};
