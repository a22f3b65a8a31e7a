//! The typed files of a run directory (`docs/run-directory.md`): one struct per file or per line of
//! a JSON-lines log, read and written by every crate through these definitions only.
//!
//! Two meanings of "split" are kept apart: a run's *task split* (`run.json`'s `task_split`: which
//! tasks are train and test tasks, "default", "ood", ...) and the tasks an evaluation is *on*
//! (`eval_on`: "test" or "train"). Run directories written before the rename call both `split`;
//! they are read through serde aliases.

use serde::{Deserialize, Deserializer, Serialize};
use std::collections::BTreeMap;

use crate::config::{within, MAX_STATE_STAT};
pub use crate::config::{LEGACY_LOSS_METRIC, LEGACY_MACAW_LOSS_METRIC};
use pdt_base::num::compact;

/// The run's identity (`run.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunInfo {
    /// The descriptive fields (`name`, `created`, `promptdt_version`) are empty when a hand-made
    /// or trimmed `run.json` lacks them: nothing reads a meaning into them.
    #[serde(default)]
    pub name: String,
    pub method: String,
    pub env: String,
    pub seed: u64,
    /// Which of the family's task splits the run trains and tests on ("default", "ood", ...).
    /// Runs on different splits are never averaged together: their test tasks differ.
    #[serde(alias = "split")]
    pub task_split: String,
    #[serde(default)]
    pub created: String,
    #[serde(default)]
    pub promptdt_version: String,
    /// The `metrics.jsonl` column that holds the method's training loss (what a report plots as
    /// "the loss"). Absent in runs written before it was recorded: see [`RunInfo::loss_metric`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_metric: Option<String>,
    /// The pack the run was trained in (`docs/packs.md`); absent for a run trained alone, so a
    /// solo run's `run.json` is what it has always been.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pack: Option<PackInfo>,
}

/// Where a run trained in a pack sat in it (`run.json`'s `pack`). Nothing reads a meaning into it
/// beyond the record: a packed run's directory is an ordinary run directory.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PackInfo {
    /// Runs in the pack when the run was created.
    pub size: usize,
    /// The run's position in the pack (0-based).
    pub slot: usize,
    /// The engine that stepped the pack: `batched` (one batched computation for all runs) or
    /// `solo` (each run's ordinary step: the run is the one trained alone, file for file). Today's
    /// solo engine takes the runs' steps one after another; a record written by an earlier
    /// version may say `solo` for a CPU pack whose steps were taken at once, one thread per run,
    /// which was exact as well, so the record means the same of the run's files either way.
    pub engine: String,
}

impl RunInfo {
    /// The `metrics.jsonl` column holding the run's training loss: the recorded one, or for runs
    /// written before it was recorded, the column their method wrote then (the one place that
    /// knows those names).
    pub fn loss_metric(&self) -> &str {
        match &self.loss_metric {
            Some(m) => m,
            None => self
                .method
                .parse::<crate::config::Method>()
                .map_or(LEGACY_LOSS_METRIC, crate::config::Method::legacy_loss_metric),
        }
    }
}

/// What evaluation needs besides weights (`task_stats.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunStats {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub state_mean: Vec<f32>,
    pub state_std: Vec<f32>,
    pub rtg_scale: f32,
    pub target_return: f32,
    pub horizon: usize,
    pub train_tasks: Vec<usize>,
    pub test_tasks: Vec<usize>,
    /// Content hashes of the training and test data (`MultiTaskDataset::fingerprint`): a resumed
    /// or evaluated run refuses data that differs. Empty in runs made before they were recorded.
    #[serde(default)]
    pub train_data_fingerprint: String,
    #[serde(default)]
    pub test_data_fingerprint: String,
}

/// The name `task_stats.json`'s struct had before it moved here.
pub type TaskStats = RunStats;

impl RunStats {
    /// The values a policy can act with: one mean and std per state dimension, finite, each std
    /// positive, all within [`MAX_STATE_STAT`]; a positive finite rtg scale; a finite target.
    pub fn check(&self) -> Result<(), String> {
        let n = self.obs_dim;
        if self.state_mean.len() != n || self.state_std.len() != n {
            return Err(format!(
                "state_mean has {} values and state_std {}, but obs_dim is {n}",
                self.state_mean.len(),
                self.state_std.len()
            ));
        }
        for (j, (&m, &s)) in self.state_mean.iter().zip(&self.state_std).enumerate() {
            let ok = within(f64::from(m), MAX_STATE_STAT)
                && s > 0.0
                && within(f64::from(s), MAX_STATE_STAT);
            if !ok {
                return Err(format!(
                    "state_mean[{j}] = {}, state_std[{j}] = {}: each must be finite and within {} \
                     in magnitude, the std positive",
                    compact(m),
                    compact(s),
                    compact(MAX_STATE_STAT)
                ));
            }
        }
        let ok =
            self.rtg_scale > 0.0 && self.rtg_scale.is_finite() && self.target_return.is_finite();
        if !ok {
            return Err(format!(
                "rtg_scale = {} must be positive and finite, target_return = {} finite",
                compact(self.rtg_scale),
                compact(self.target_return)
            ));
        }
        Ok(())
    }

    /// Compares the statistics recomputed from the data now with those recorded in a run;
    /// `Err` says what differs. Fingerprints are compared when the run recorded them.
    pub fn check_same_as(&self, recorded: &RunStats) -> Result<(), DataMismatch> {
        let fp = |now: &str, then: &str, which: &'static str| {
            if !then.is_empty() && now != then {
                Err(DataMismatch::Fingerprint { which, then: then.into(), now: now.into() })
            } else {
                Ok(())
            }
        };
        fp(&self.train_data_fingerprint, &recorded.train_data_fingerprint, "training")?;
        fp(&self.test_data_fingerprint, &recorded.test_data_fingerprint, "test")?;
        let mut mine = self.clone();
        mine.train_data_fingerprint.clone_from(&recorded.train_data_fingerprint);
        mine.test_data_fingerprint.clone_from(&recorded.test_data_fingerprint);
        if &mine != recorded {
            return Err(DataMismatch::Statistics);
        }
        Ok(())
    }
}

/// How the data a run is resumed or evaluated with differ from what it trained on: other files
/// (their fingerprint), or other statistics, tasks or return settings (another configuration).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DataMismatch {
    #[error("the {which} data differ from what the run trained on ({then}, now {now})")]
    Fingerprint { which: &'static str, then: String, now: String },
    #[error(
        "the state statistics, tasks or return settings recomputed from the configuration and \
         data differ from those the run recorded"
    )]
    Statistics,
}

/// The commit point of a checkpoint (`checkpoints/latest.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Latest {
    pub step: u64,
    pub iteration: u64,
    /// The weights file, `step_<step>.safetensors`, in `checkpoints/`.
    pub model: String,
    /// The optimiser state file, `state_<step>.safetensors`, in `checkpoints/`.
    pub state: String,
    /// `false` for a resume point between checkpoints (`train.resume_interval`): its weights are
    /// removed once a later checkpoint is in force. Absent in runs written before the option.
    #[serde(default = "keep_default")]
    pub keep: bool,
}

fn keep_default() -> bool {
    true
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

impl Latest {
    /// The weights file name a checkpoint of `step` has.
    pub fn model_name(step: u64) -> String {
        format!("step_{step}.safetensors")
    }

    /// The optimiser state file name a checkpoint of `step` has.
    pub fn state_name(step: u64) -> String {
        format!("state_{step}.safetensors")
    }

    /// `Err` says why the record does not name its own step's weights (an edited or corrupt file).
    pub fn check(&self) -> Result<(), String> {
        if self.model != Self::model_name(self.step) {
            return Err(format!("names weights `{}` for step {}", self.model, self.step));
        }
        Ok(())
    }
}

/// Training state besides weights and moments (`checkpoints/state_<N>.json`): what a resumed run
/// restores, and what the clean-up of a killed run reads (`keep`). The fields are in the order the
/// files of earlier versions have them, so that a run's files stay byte-identical.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    /// The method whose state this is, for the methods that record it (MACAW: `"macaw"`; absent
    /// for the Prompt-DT variants, whose files never had it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<String>,
    pub iteration: u64,
    pub step: u64,
    /// Position of the batch-sampling RNG (a u128, as a decimal string).
    pub batch_rng_word_pos: String,
    /// The optimiser steps taken, in the method's own layout (opaque here: each method writes
    /// and checks its own).
    pub adam_steps: serde_json::Value,
    /// Lines of `metrics.jsonl` and `eval.jsonl` at the checkpoint: a resumed run cuts the logs
    /// back to them.
    pub metrics_lines: usize,
    pub eval_lines: usize,
    /// Lines of `offline_eval.jsonl` at the checkpoint (a run evaluated offline,
    /// `crate::offline`); absent when 0, so the files of every other run are as before.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub offline_eval_lines: usize,
    /// As `latest.json`'s `keep`: `false` for a resume point, whose files go once a later one is
    /// in force. Recorded here too, so a removal cut short by a kill is finished on the next
    /// start. Absent in runs written before it was recorded (then kept).
    #[serde(default = "keep_default")]
    pub keep: bool,
}

/// One task's evaluation: the rows of `eval_final.json`'s `tasks`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskResult {
    pub task: String,
    pub task_index: usize,
    /// serde_json writes a NaN (a diverged policy) as `null`; it reads back as NaN.
    #[serde(deserialize_with = "f64_or_null")]
    pub return_mean: f64,
    #[serde(deserialize_with = "f64_or_null")]
    pub return_std: f64,
    #[serde(deserialize_with = "f64_or_null")]
    pub length_mean: f64,
    pub episodes: usize,
    #[serde(deserialize_with = "f64s_or_null")]
    pub returns: Vec<f64>,
    /// Fraction of the episodes that succeeded; `None` for families without a success criterion.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub success_rate: Option<f64>,
}

/// The final evaluation of a run's latest checkpoint (`eval_final.json`, by `promptdt eval`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinalEval {
    pub iteration: u64,
    pub step: u64,
    pub checkpoint: String,
    /// The tasks evaluated on: "test" or "train".
    #[serde(alias = "split")]
    pub eval_on: String,
    pub tasks: Vec<TaskResult>,
    #[serde(deserialize_with = "f64_or_null")]
    pub mean_return: f64,
    /// The budget of the test-time adaptation of the learner's own weights, for those that
    /// record one here (`Adaptation::recorded`: MACAW's, "2 steps on 4 transitions"); absent
    /// otherwise (`[eval.adapt]`'s is in `eval_adapt_<kind>.json`, fine-tuning's in the config).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptation: Option<String>,
    /// `promptdt eval --repeats N` (N > 1): the evaluation repeated over independent prompt
    /// draws and reset seeds, the fields above being repeat 0's (what the evaluation without the
    /// flag gives). Absent for one evaluation, so such a file is as before.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub repeats: Option<EvalRepeats>,
}

/// The repeats of one evaluation (`eval_*.json`'s `repeats`): what the evaluation noise of one
/// set of weights is, apart from the noise between training seeds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalRepeats {
    /// Where repeat r's draws come from (the run seed's evaluation stream at a counter of its
    /// own; docs/run-directory.md).
    pub streams: String,
    /// Per repeat (repeat 0 first), per task in `tasks` order: the task's mean return.
    #[serde(deserialize_with = "f64s2_or_null")]
    pub task_returns: Vec<Vec<f64>>,
    /// Per repeat: the mean over tasks of `task_returns` (repeat 0's is `mean_return`).
    #[serde(deserialize_with = "f64s_or_null")]
    pub mean_returns: Vec<f64>,
    /// Sample standard deviation (n - 1) of `mean_returns`: the evaluation noise of the mean.
    #[serde(deserialize_with = "f64_or_null")]
    pub mean_return_sd: f64,
    /// Per task: the sample standard deviation of its mean return over the repeats.
    #[serde(deserialize_with = "f64s_or_null")]
    pub task_return_sd: Vec<f64>,
}

impl EvalRepeats {
    /// The repeats' record from each repeat's per-task mean returns (repeat 0 first).
    pub fn of(streams: String, task_returns: Vec<Vec<f64>>) -> Self {
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let sd = |v: &[f64]| {
            if v.len() < 2 {
                return 0.0;
            }
            let m = mean(v);
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
        };
        let mean_returns: Vec<f64> = task_returns.iter().map(|r| mean(r)).collect();
        let tasks = task_returns.first().map_or(0, Vec::len);
        let task_return_sd = (0..tasks)
            .map(|t| sd(&task_returns.iter().map(|r| r[t]).collect::<Vec<_>>()))
            .collect();
        Self {
            streams,
            mean_return_sd: sd(&mean_returns),
            mean_returns,
            task_returns,
            task_return_sd,
        }
    }
}

/// A final evaluation with a prompt strategy other than the default (`promptdt eval
/// --prompt-strategy`): `eval_prompt_<strategy>.json`, beside `eval_final.json` (which stays the
/// reference rule's, as reports read it). Its `picks` log each strategy choice (for a bandit,
/// every round's arms and whether it explored).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PromptEval {
    #[serde(flatten)]
    pub eval: FinalEval,
    pub prompt_strategy: pdt_prompt::PromptStrategy,
    pub picks: Vec<pdt_prompt::PromptPick>,
    /// `[eval.adapt]` when an adaptation was used (then the file is `eval_adapt_<kind>.json`).
    #[serde(default, skip_serializing_if = "crate::config::AdaptConfig::is_none")]
    pub adapt: crate::config::AdaptConfig,
    /// Per test task: the demonstrations' action loss before and after, budget, wall time.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub adapt_log: Vec<crate::config::AdaptLog>,
}

/// One line of `eval.jsonl`: one task's evaluation at one iteration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalLine {
    pub iteration: u64,
    pub step: u64,
    /// The tasks evaluated on: "test" or "train".
    #[serde(alias = "split")]
    pub eval_on: String,
    pub task: String,
    pub task_index: usize,
    /// serde_json writes a NaN (a diverged policy) as `null`; it reads back as NaN.
    #[serde(deserialize_with = "f64_or_null")]
    pub return_mean: f64,
    #[serde(deserialize_with = "f64_or_null")]
    pub return_std: f64,
    #[serde(deserialize_with = "f64_or_null")]
    pub length_mean: f64,
    pub episodes: usize,
    pub target_return: f32,
    /// Only families with a success criterion (Meta-World) have the column.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub success_rate: Option<f64>,
    /// How a test-time adaptation of the learner's own weights went on this task (the steps it
    /// took and the episodes a non-finite action ended), for the adaptations that record them
    /// (today MACAW's, the one that adapts on training tasks too); absent otherwise.
    #[serde(flatten)]
    pub adaptation: Option<AdaptationStats>,
}

/// A test-time adaptation's record of one task (columns of its `eval.jsonl` line): how far its
/// gradient steps went and what its episodes met.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct AdaptationStats {
    /// Adaptation steps taken (of the value function, then of the policy): fewer than the budget
    /// (MACAW's `macaw.adapt_steps`) where the adaptation diverged.
    pub adapt_value_steps: usize,
    pub adapt_policy_steps: usize,
    /// Episodes ended by a non-finite action.
    pub failed_episodes: usize,
}

impl EvalLine {
    /// The line of `result`, evaluated at `iteration` (`step`) on `eval_on` ("test" or "train")
    /// with the run's target return.
    pub fn new(r: &TaskResult, iteration: u64, step: u64, eval_on: &str, target: f32) -> Self {
        Self {
            iteration,
            step,
            eval_on: eval_on.into(),
            task: r.task.clone(),
            task_index: r.task_index,
            return_mean: r.return_mean,
            return_std: r.return_std,
            length_mean: r.length_mean,
            episodes: r.episodes,
            target_return: target,
            success_rate: r.success_rate,
            adaptation: None,
        }
    }

    /// Whether the line is an evaluation of the run's test tasks.
    pub fn is_test(&self) -> bool {
        self.eval_on == "test"
    }
}

/// One line of `metrics.jsonl`: one iteration's training statistics. The fixed keys are fields;
/// the method's own statistics (`train/action_loss`, `train/policy_outer_loss`, ...) are data,
/// named by the method ([`RunInfo::loss_metric`] says which one is the loss).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetricsLine {
    pub iteration: u64,
    pub step: u64,
    /// Training time of the kept iterations so far (a resumed run adds its own time).
    #[serde(rename = "time/elapsed_s", deserialize_with = "f64_or_null")]
    pub elapsed_s: f64,
    /// The method's statistics by column name; a NaN is written as `null` and read back as NaN.
    #[serde(flatten, deserialize_with = "nan_map_de")]
    pub values: BTreeMap<String, f64>,
}

impl MetricsLine {
    /// The value of the column `name`, if the line has it.
    pub fn get(&self, name: &str) -> Option<f64> {
        self.values.get(name).copied()
    }
}

fn f64_or_null<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

fn f64s2_or_null<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<Vec<f64>>, D::Error> {
    let rows = Vec::<Vec<Option<f64>>>::deserialize(d)?;
    Ok(rows.into_iter().map(|r| r.into_iter().map(|x| x.unwrap_or(f64::NAN)).collect()).collect())
}

fn f64s_or_null<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
    Ok(Vec::<Option<f64>>::deserialize(d)?.into_iter().map(|x| x.unwrap_or(f64::NAN)).collect())
}

fn nan_map_de<'de, D: Deserializer<'de>>(d: D) -> Result<BTreeMap<String, f64>, D::Error> {
    Ok(BTreeMap::<String, Option<f64>>::deserialize(d)?
        .into_iter()
        .map(|(k, v)| (k, v.unwrap_or(f64::NAN)))
        .collect())
}
