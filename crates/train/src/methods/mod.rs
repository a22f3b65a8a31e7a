//! The trainable methods, each behind [`Learner`], and the registry that maps a configuration's
//! `run.method` to one. The loop (`run_loop`) and the final evaluation (`evaluate`) own everything
//! a run has whatever its method (cadence, logs, checkpoint commits, resume points, RNG restore,
//! progress); a learner owns its model, optimiser, sampling, evaluation and tensor files.
//!
//! A new method: its module here, one line in [`learner`], and its section of the configuration
//! (`docs/adding-a-method.md`).

mod adapt;
mod learner;
pub(crate) mod macaw;
mod planned;
pub(crate) mod prompt_dt;
mod prompt_strategy;

pub use learner::MacawAdaptation;
pub(crate) use learner::{
    CheckpointFiles, IterationAt, IterationMetrics, Learner, SavedSteps, TaskEval,
};

use crate::config::Method;
use crate::error::RunError;
use crate::setup::Setup;

/// The registry: the learner of the run's method, its model initialised from the run seed.
/// Call it with libtorch's generator held (`streams::torch_rng_lock`).
pub(crate) fn learner<'s>(setup: &'s Setup) -> Result<Box<dyn Learner + 's>, RunError> {
    Ok(match setup.cfg.run.method {
        m @ (Method::PromptDt | Method::PromptMtBc | Method::MtOrl | Method::MtBcFinetune) => {
            Box::new(prompt_dt::PromptDtLearner::new(setup, prompt_dt::Variant::of(m))?)
        }
        Method::Macaw => Box::new(macaw::MacawLearner::new(setup)?),
    })
}
