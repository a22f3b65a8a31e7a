//! What a task suite says about its environment: how a worker process makes one task's
//! environment. Plain data, validated where it is read (the suite file).

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// How a Python worker makes the environment of one task (a suite's `[environment]` table).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorkerSpec {
    /// What makes one task's environment: a gymnasium id (`"Pendulum-v1"`) or a Python
    /// `"module:callable"` returning a `gymnasium.Env`.
    pub entry: String,
    /// The keyword argument through which a task's parameters (its `params` table in the suite)
    /// reach `entry`: `entry(**kwargs, **{task_keyword: params})`. `None`: the parameters' own
    /// entries are passed as keyword arguments, `entry(**kwargs, **params)`.
    #[serde(default)]
    pub task_keyword: Option<String>,
    /// Keyword arguments given to `entry` for every task.
    #[serde(default)]
    pub kwargs: serde_json::Map<String, serde_json::Value>,
    /// Modules the worker imports before making environments (e.g. one that registers gymnasium
    /// ids, `"metaworld"`).
    #[serde(default)]
    pub imports: Vec<String>,
    /// The Python interpreter that runs the worker; it must import `promptdt` and the
    /// environment's package. `None`: `$PROMPTDT_PYTHON`, else `python3` on `PATH`. A relative path
    /// is taken from the suite file's directory; a bare name (`python3.11`) is looked up on `PATH`.
    #[serde(default)]
    pub python: Option<PathBuf>,
    /// Seconds one vector step (or reset) may take before the worker counts as hung.
    #[serde(default = "default_step_timeout_s")]
    pub step_timeout_s: f64,
}

fn default_step_timeout_s() -> f64 {
    60.0
}

/// One task of a suite, as a worker needs it to make the task's environment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorkerTask {
    /// The task's index in its suite.
    pub index: usize,
    /// The task's name in its suite.
    pub name: String,
    /// The task's parameters (a JSON object).
    pub params: serde_json::Value,
}
