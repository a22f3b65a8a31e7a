//! A trained run as a policy: what `promptdt serve` (HTTP) and the Python package (numpy) act
//! through, so both load, prompt, step and check the same way.
//!
//! - [`Policy`] ([`policy`]): a run's latest weights loaded to act, with its normalisation, return
//!   tokens and K; prompts from arrays ([`PromptArrays`]) or drawn from the run's data as its
//!   evaluation draws them; its evaluation's plans ([`Policy::eval_plan`]).
//! - [`Episode`] ([`episode`]): one episode's history and checks (observation, reward, target
//!   return, `max_ep_len`, return-to-go overflow), and the undo of a step whose action is not
//!   finite.
//! - Test time for an acting policy (`testtime.rs`): the prompt a strategy picks
//!   ([`Policy::strategy_prompt`]), a task's bandit ([`Policy::task_bandit`]) and a task's
//!   adaptation ([`Policy::adapt`]), each through `pdt_eval::testtime`, which owns them.
//! - [`RunData`] ([`data`]): a configuration's data loaded and checked, with the state
//!   normalisation and the statistics a run records.
//! - [`video`]: a prompted episode rendered as an animated GIF (`promptdt render`).
//! - [`files`]: the run-directory files acting on a run reads (its configuration with this
//!   invocation's device and data place, `task_stats.json` checked, the latest checkpoint), with
//!   what a missing or bad one means; the trainer's final evaluation and resume read them here too.

// Errors carry the offending path or value; they are returned on the cold path only.
#![allow(clippy::result_large_err)]

pub mod data;
pub mod episode;
mod error;
pub mod files;
mod font;
mod inputs;
pub mod policy;
mod testtime;
pub mod video;

pub use data::RunData;
pub use episode::{Episode, Observation, Step, Target};
pub use error::PolicyError;
pub use inputs::{Inputs, MAX_RETURN};
pub use pdt_rundir::RunStats;
pub use policy::{eval_returns, Policy, PromptArrays};
