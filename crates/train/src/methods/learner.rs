//! The [`Learner`] trait: what the run loop asks of a method, and the types it speaks in; and
//! [`Steppable`], what a pack asks of a method besides.

use crate::error::{io_err, RunError};
use crate::optim::SlotState;
use crate::run_dir::temp_name;
use crate::setup::Split;
use crate::step::DeviceBatch;
use pdt_prompt::Rng;
use pdt_rundir::config::TestTime;
use pdt_rundir::AdaptationStats;
use pdt_rundir::OfflineTaskResult;
use pdt_rundir::TaskResult;
use std::collections::BTreeMap;
use std::path::Path;
use tch::Tensor;

/// Where one training iteration stands, for [`Learner::train_iteration`].
#[derive(Debug, Clone, Copy)]
pub struct IterationAt<'a> {
    /// The run directory (named in errors).
    pub(crate) dir: &'a Path,
    /// The iteration being trained, from 1.
    pub(crate) iteration: u64,
    /// Gradient steps taken before it.
    pub first_step: u64,
    /// Gradient steps it takes (`train.steps_per_iteration`).
    pub steps: u64,
    /// Checked before each step: one iteration can outlast a user's patience for Ctrl-C.
    pub(crate) interrupt: &'a pdt_base::stop::StopFlag,
}

impl IterationAt<'_> {
    /// Takes the iteration's `steps` gradient steps, `one(step)` each (`step` counted from
    /// `first_step`), and returns their statistics; the first error (a divergence, or
    /// [`RunError::Interrupted`] when a stop was asked for before a step) ends it.
    pub fn each_step<S>(
        &self,
        mut one: impl FnMut(u64) -> Result<S, RunError>,
    ) -> Result<Vec<S>, RunError> {
        (self.first_step..self.first_step + self.steps)
            .map(|step| {
                if self.interrupt.is_set() {
                    return Err(RunError::Interrupted {
                        dir: self.dir.into(),
                        iteration: self.iteration,
                    });
                }
                one(step)
            })
            .collect()
    }
}

/// What one training iteration logs.
#[derive(Debug, Clone)]
pub struct IterationMetrics {
    /// The mean training loss over its steps, logged under [`Learner::loss_metric`] and reported
    /// as progress.
    pub(crate) loss: f64,
    /// The learner's other `metrics.jsonl` columns by name (the loop adds `iteration`, `step`,
    /// `time/elapsed_s` and the loss): `pdt_rundir::MetricsLine::values`.
    pub(crate) columns: BTreeMap<String, f64>,
}

/// One task's evaluation.
#[derive(Debug, Clone)]
pub struct TaskEval {
    pub(crate) result: TaskResult,
    /// MACAW: the adaptation steps taken and the episodes a non-finite action ended (columns of
    /// the task's `eval.jsonl` line); `None` for the methods without an adaptation.
    pub(crate) adaptation: Option<AdaptationStats>,
}

/// One evaluation of a split: every task's result and what the test-time behaviour chose on the
/// way, returned together (no learner keeps them for a later call to take).
#[derive(Debug, Clone, Default)]
pub struct Evaluation {
    pub(crate) tasks: Vec<TaskEval>,
    /// The prompt strategy's choices (`[eval.prompt]`); empty for the reference rule and the
    /// methods without a prompt.
    pub(crate) picks: Vec<pdt_prompt::PromptPick>,
    /// What `[eval.adapt]`'s adaptation did per test task; empty without one.
    pub(crate) adapt_log: Vec<pdt_rundir::config::AdaptLog>,
}

impl Evaluation {
    /// The evaluation of `tasks` by a rule that chooses nothing on the way.
    pub(crate) fn of_tasks(tasks: Vec<TaskEval>) -> Self {
        Self { tasks, ..Self::default() }
    }
}

/// The files of one checkpoint, named by its step (`checkpoints/step_<N>.safetensors` for weights,
/// `state_<N>.safetensors` for optimiser moments).
#[derive(Debug, Clone)]
pub struct CheckpointFiles {
    pub(crate) weights: std::path::PathBuf,
    pub(crate) moments: std::path::PathBuf,
    /// The state file (`state_<N>.json`), named in errors about what it records.
    pub(crate) state: std::path::PathBuf,
}

/// The state file's answer to "how far did the optimiser go": the step of the checkpoint, and the
/// learner's own record ([`Learner::save`]'s return) of its optimiser steps.
#[derive(Debug, Clone, Copy)]
pub struct SavedSteps<'a> {
    pub(crate) step: u64,
    pub(crate) adam_steps: &'a serde_json::Value,
}

/// Writes `tensors` to `path` as safetensors under a temporary name first (one that
/// `pdt_base::fs::remove_stale_temps` recognises), then renamed: a kill mid-write leaves the
/// previous file or none.
pub(crate) fn write_tensors(path: &Path, tensors: &[(String, Tensor)]) -> Result<(), RunError> {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(temp_name(&name));
    Tensor::write_safetensors(tensors, &tmp)
        .map_err(|e| RunError::Corrupt { path: tmp.clone(), message: e.to_string() })?;
    std::fs::rename(&tmp, path).map_err(io_err(&tmp))
}

/// A learner's record of its optimiser steps, as the state file's `adam_steps`.
pub(crate) fn adam_steps_value<T: serde::Serialize>(
    steps: &T,
    files: &CheckpointFiles,
) -> Result<serde_json::Value, RunError> {
    serde_json::to_value(steps)
        .map_err(|e| RunError::Corrupt { path: files.state.clone(), message: e.to_string() })
}

/// The state file's `adam_steps` in a learner's own layout.
pub(crate) fn adam_steps_of<T: serde::de::DeserializeOwned>(
    saved: SavedSteps<'_>,
    files: &CheckpointFiles,
) -> Result<T, RunError> {
    serde_json::from_value(saved.adam_steps.clone()).map_err(|e| RunError::Corrupt {
        path: files.state.clone(),
        message: format!("adam_steps: {e}"),
    })
}

/// A trainable method: a model with its optimiser, trained in iterations of gradient steps on
/// batches it samples itself, evaluated on the test or training tasks, saved and loaded.
pub trait Learner {
    /// The `metrics.jsonl` column of the training loss (`train/action_loss`).
    fn loss_metric(&self) -> &'static str;

    /// What the state file records as `method` (MACAW: `"macaw"`); `None`: nothing, as the
    /// Prompt-DT variants' files have always been. A state file of another tag is refused.
    fn state_tag(&self) -> Option<&'static str> {
        None
    }

    /// Refuses, before training starts, a configuration its data cannot serve (batches larger than
    /// a task's data), naming the task.
    fn check_can_train(&self) -> Result<(), RunError> {
        Ok(())
    }

    /// One iteration of `at.steps` gradient steps, batches drawn from `rng` (the run's batch
    /// stream, whose position the loop saves and restores).
    fn train_iteration(
        &mut self,
        at: IterationAt<'_>,
        rng: &mut Rng,
    ) -> Result<IterationMetrics, RunError>;

    /// Evaluates every task of `split` with the current weights as `test_time` says (the run's
    /// own: [`TestTime::of`]; an evaluation's request may change it), drawing from `rng` (a
    /// stream of the run seed apart from training's), and leaves the weights as they were. A
    /// test time the learner has no means for (MACAW's adaptation for a transformer) is refused.
    fn evaluate(
        &mut self,
        split: Split,
        test_time: &TestTime,
        rng: &mut Rng,
    ) -> Result<Evaluation, RunError>;

    /// The offline evaluation of `split` with the current weights (`pdt_eval::offline`: the
    /// action error on the split's data, drawing from `rng`), for a run with no environment to
    /// act in; `None` for a learner that has none (MACAW's policy is no prompted sequence model).
    fn offline_evaluate(
        &mut self,
        _split: Split,
        _rng: &mut Rng,
    ) -> Result<Option<Vec<OfflineTaskResult>>, RunError> {
        Ok(None)
    }

    /// Writes the weights and optimiser moments to `files`; returns what the state file records
    /// as `adam_steps`. (`&mut`: a run of a pack takes its weights back from the pack's engine
    /// first, `pdt-pack`.)
    fn save(&mut self, files: &CheckpointFiles) -> Result<serde_json::Value, RunError>;

    /// Restores weights and optimiser from `files`, checking the state file's record `saved`.
    fn load(&mut self, files: &CheckpointFiles, saved: SavedSteps<'_>) -> Result<(), RunError>;

    /// Loads weights alone (a final evaluation), each tensor by name and shape.
    fn load_weights(&mut self, path: &Path) -> Result<(), RunError>;
}

/// A [`Learner`] whose gradient steps a pack's engine can take (`pdt-pack`, docs/packs.md): it
/// samples its batches, hands its weights and optimiser state to the engine and takes them back;
/// its evaluations and files stay its own. The registry returns one only for a method that
/// `Method::packs` (`super::steppable`).
pub trait Steppable: Learner {
    /// The next training batch from the run's batch stream (`rng`), on the run's device: the
    /// batch its own [`Learner::train_iteration`] would step on.
    fn sample_batch(&self, rng: &mut Rng) -> DeviceBatch;

    /// The weights and optimiser state, copied (the learner's own are never shared).
    fn export(&self) -> SlotState;

    /// Sets the weights (each by name and shape) and the optimiser state.
    fn import(&mut self, state: SlotState) -> Result<(), RunError>;

    /// Before an evaluation of `split`: whether it draws from libtorch's random generator
    /// (MT-BC-Finetune's fine-tuning dropout), and if so the generator put where the run's own
    /// gradient step `last` (its index and batch) left it, as it stands after that step in a run
    /// trained alone. A packed run's generator has since served the other runs; the pack holds it
    /// through such an evaluation. Call it with `crate::streams::torch_rng_lock` held.
    fn replay_step_draws(&self, split: Split, last: Option<(u64, &DeviceBatch)>) -> bool;
}
