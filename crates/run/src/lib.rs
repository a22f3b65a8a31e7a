//! A run, apart from acting with it: what the trainer and an acting policy (`pdt-policy`) both
//! read of a run, so that training, evaluation, serving and the Python package load, check and
//! draw alike.
//!
//! - [`RunData`] ([`data`]): a configuration's data loaded and checked, with the state
//!   normalisation, the sampler's and model's settings and the statistics a run records.
//! - [`files`]: the run-directory files using a run reads (its configuration with this
//!   invocation's device and data place, `task_stats.json` checked, the latest checkpoint), with
//!   what a missing or bad one means.
//! - [`streams`]: the run seed's independent random streams.
//! - [`plan`]: what an evaluation draws for each task ([`TaskPlan`]) and the return tokens it
//!   feeds.
//!
//! The run directory's schema itself (`config.toml` and every file's rows) is `pdt-rundir`'s, which
//! is free of libtorch; this crate needs the model's shape and the environments, so it is not.

// Errors carry the offending path or value; they are returned on the cold path only.
#![allow(clippy::result_large_err)]

pub mod data;
mod error;
pub mod files;
pub mod plan;
pub mod streams;

pub use data::RunData;
pub use error::LoadError;
pub use plan::eval_returns;
