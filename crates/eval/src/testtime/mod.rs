//! Test time: what an evaluation or an acting policy does besides acting with the trained weights
//! and the reference prompt, one owner for every caller (`promptdt eval` through `pdt-train`'s
//! learners, `promptdt serve` and the Python `Policy` through `pdt_policy::Policy`). A
//! [`TestTime`] value (`pdt_rundir`'s, read without libtorch) says which:
//!
//! - **planning** ([`plan`]): each task's prompt and reset seeds as the reference evaluation
//!   draws them, which every test time of an evaluation starts from;
//! - **selection** ([`select`]): the prompt a strategy picks per task, per episode or per bandit
//!   round, and the log of its choices;
//! - **adaptation** ([`adapt`], [`task`]): `[eval.adapt]`'s soft prompt, Prompt-Tuning DT and
//!   LoRA, learned from a task's demonstrations with the backbone frozen, full fine-tuning of
//!   every weight at their budget (changed for a task's episodes, then restored bit for bit), and
//!   their [`optim`]iser. The adaptations of a learner's
//!   own weights ([`Adaptation::Finetune`], MT-BC-Finetune's; [`Adaptation::Macaw`], MACAW's) are
//!   kinds of the same value, carried out by their learners (`pdt-train`), which own the weights
//!   and the optimiser that trained them.
//!
//! - **a split's evaluation** ([`split`]) under the reference rule, a strategy or an
//!   `[eval.adapt]` adaptation, which a learner's `evaluate` calls with its model.
//!
//! So this crate evaluates and adapts at test time; it never trains a run's weights (full
//! fine-tuning changes them for one task's episodes and puts them back).

pub mod adapt;
mod optim;
pub mod plan;
pub mod select;
pub mod split;
pub mod task;

use pdt_rundir::config::{AdaptConfig, AdaptError, AdaptKind, AdaptLog, PtdtScore};
pub use plan::{plan_task, summarise_plans, SplitEval, TaskPlan};
pub use select::{choose_prompt, ChosenPrompt, NearestStart, TaskBandit};
pub use split::{evaluate_adapted, evaluate_reference, evaluate_strategy, SplitResult};
pub use task::{adapt_task, check_adaptable, start_prompt, AdaptTask, Adapted, TaskAdaptation};

/// What test time refuses or fails at, for its callers to map to their own errors.
#[derive(Debug, thiserror::Error)]
pub enum TestTimeError {
    /// A request it cannot serve, named: a method without a prompt, a strategy that picks per
    /// episode where one per task is needed, settings out of range, a missing observation.
    #[error("{0}")]
    Input(String),
    /// An adaptation that failed on the way (a non-finite loss), naming the task.
    #[error("{0}")]
    Failed(String),
    #[error(transparent)]
    Sampler(#[from] pdt_prompt::SamplerError),
    #[error(transparent)]
    Strategy(#[from] pdt_prompt::StrategyError),
    #[error(transparent)]
    Env(#[from] pdt_envs::EnvError),
    #[error(transparent)]
    Eval(#[from] crate::EvalError),
}
