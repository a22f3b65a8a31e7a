//! The public face of a run: [`train`] (the loop in `run_loop`, the methods in `methods`) and
//! [`evaluate_run`] (the final evaluation, `evaluate`). The run directory's records are
//! `pdt_rundir`'s, its data, files, streams and evaluation plans `pdt_run`'s; a trained run loaded
//! to act is `pdt_policy::Policy`.
//!
//! Randomness: one seed, split into independent streams (model init, batch sampling, dropout per
//! gradient step, evaluation per iteration), so a resumed run draws exactly what an uninterrupted one
//! would, and evaluation never disturbs training.

pub use crate::error::RunError;
pub use crate::evaluate::{
    asked_test_time, evaluate_run, evaluate_run_as, evaluate_run_in, EnvMaker, EvalRequest,
};
pub use crate::offline::{evaluate_run_offline, evaluates_offline};
pub use crate::run_loop::{
    run_config_for, train, train_learner, Progress, ResumeWith, TrainOptions, TrainSummary,
};
