//! A trained run as a policy: what `promptdt serve` (HTTP) and the Python package (numpy) act
//! through, so both load, prompt, step and check the same way.
//!
//! - [`Policy`] ([`policy`]): a run's latest weights loaded to act, with its normalisation, return
//!   tokens and K; prompts from arrays ([`PromptArrays`]) or drawn from the run's data as its
//!   evaluation draws them; evaluation plans (`pdt_eval::testtime::TaskPlan`).
//! - [`Episode`] ([`episode`]): one episode's history and checks (observation, reward, target
//!   return, `max_ep_len`, return-to-go overflow), and the undo of a step whose action is not
//!   finite.
//! - [`Inputs`]: what a policy accepts as input, and the record of a step's largest input.
//! - Test time for an acting policy (`testtime.rs`): the prompt a strategy picks
//!   ([`Policy::strategy_prompt`]), a task's bandit ([`Policy::task_bandit`]) and a task's
//!   adaptation ([`Policy::adapt`]), each through `pdt_eval::testtime`, which owns them.
//!
//! What is a run's rather than a policy's (its data loader, run-directory files, seed streams)
//! is `pdt-run`'s, read by the trainer too; filming an episode is the CLI's (`promptdt render`).

// Errors carry the offending path or value; they are returned on the cold path only.
#![allow(clippy::result_large_err)]

pub mod episode;
mod error;
mod inputs;
pub mod policy;
mod testtime;

pub use episode::{Episode, Observation, Step, Target};
pub use error::PolicyError;
pub use inputs::{Inputs, MAX_RETURN};
pub use policy::{Policy, PromptArrays};
