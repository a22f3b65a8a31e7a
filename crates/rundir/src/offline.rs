//! The records of an offline evaluation (`docs/run-directory.md`): the prompted model's action
//! error on the held-out tasks' data, for runs with no environment to act in (a task suite
//! without `[environment]`). Files of their own, never `eval.jsonl` or `eval_final.json`: an
//! action error is not a return, and no reader of returns may take one for a return.

use serde::{Deserialize, Deserializer, Serialize};

/// The metric every offline record holds (its files' `metric` and the report's label).
pub const OFFLINE_METRIC: &str = "action_mse";

/// What the metric measures, in one sentence (recorded in `eval_offline.json`, quoted by docs).
pub const OFFLINE_MEASURE: &str = "mean squared error of the predicted actions against the data's \
     actions over the valid steps of history segments sampled from each task's dataset as \
     training samples them, each task's segments given the prompt its evaluation draws; lower is \
     better";

/// One task's action error (a line of `offline_eval.jsonl`, a row of `eval_offline.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OfflineTaskResult {
    pub task: String,
    pub task_index: usize,
    /// Mean over the valid steps and action dimensions of (predicted - data action)^2, in the
    /// action's units. serde_json writes a NaN (a diverged model) as `null`; it reads back as NaN.
    #[serde(deserialize_with = "f64_or_null")]
    pub action_mse: f64,
    /// History segments measured.
    pub segments: usize,
    /// Valid (unpadded) steps over those segments: the terms of the mean, per action dimension.
    pub steps: usize,
}

/// One line of `offline_eval.jsonl`: one task's offline evaluation at one iteration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OfflineEvalLine {
    pub iteration: u64,
    pub step: u64,
    /// The tasks evaluated on: "test" (the held-out tasks) or "train".
    pub eval_on: String,
    #[serde(flatten)]
    pub result: OfflineTaskResult,
}

impl OfflineEvalLine {
    /// Whether the line is an evaluation of the run's test tasks.
    pub fn is_test(&self) -> bool {
        self.eval_on == "test"
    }
}

/// An offline evaluation of a run's latest checkpoint (`eval_offline.json`, by `promptdt eval`
/// on a run with no environment).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OfflineEval {
    /// Always [`OFFLINE_METRIC`].
    pub metric: String,
    /// [`OFFLINE_MEASURE`] as it was when written.
    pub measure: String,
    pub iteration: u64,
    pub step: u64,
    pub checkpoint: String,
    /// "test" or "train".
    pub eval_on: String,
    /// History segments per task (`eval.offline_segments`).
    pub segments_per_task: usize,
    pub tasks: Vec<OfflineTaskResult>,
    /// Mean over tasks of `action_mse`.
    #[serde(deserialize_with = "f64_or_null")]
    pub mean_action_mse: f64,
}

impl OfflineEval {
    /// The mean over `tasks` of their action error.
    pub fn mean_of(tasks: &[OfflineTaskResult]) -> f64 {
        tasks.iter().map(|t| t.action_mse).sum::<f64>() / tasks.len().max(1) as f64
    }
}

impl std::fmt::Display for OfflineEval {
    /// `offline evaluation on test tasks at iteration 10: action MSE g3 0.0123, ...; average
    /// 0.0150 (lower is better)`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "offline evaluation (no environment) on {} tasks at iteration {}: action MSE",
            self.eval_on, self.iteration
        )?;
        for (i, t) in self.tasks.iter().enumerate() {
            let sep = if i == 0 { " " } else { ", " };
            write!(f, "{sep}{} {:.4}", t.task, t.action_mse)?;
        }
        write!(f, "; average {:.4} (lower is better; not a return)", self.mean_action_mse)
    }
}

fn f64_or_null<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A line is flat (the task's fields beside the iteration's, as `eval.jsonl`'s are), and a
    /// NaN error written as `null` reads back as NaN.
    #[test]
    fn a_line_is_flat_and_a_nan_round_trips() {
        let line = OfflineEvalLine {
            iteration: 3,
            step: 30,
            eval_on: "test".into(),
            result: OfflineTaskResult {
                task: "g3".into(),
                task_index: 3,
                action_mse: f64::NAN,
                segments: 8,
                steps: 70,
            },
        };
        let text = serde_json::to_string(&line).unwrap();
        assert!(text.contains("\"action_mse\":null") && text.contains("\"task\":\"g3\""), "{text}");
        let back: OfflineEvalLine = serde_json::from_str(&text).unwrap();
        assert!(back.result.action_mse.is_nan() && back.is_test());
        assert_eq!(back.result.steps, 70);
    }
}
