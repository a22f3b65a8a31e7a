//! The run directory's schema, with no libtorch below it: what a run directory holds, owned in one
//! place so that the trainer, the evaluator, the report, `reproduce`, the server and the Python
//! package read and write the same typed files.
//!
//! - [`config`]: `config.toml`, the whole experiment ([`config::TrainConfig`]) with every option type
//!   it names (the optimiser's, the loss's, the evaluator's, MACAW's), so that a crate can read a
//!   run's configuration without linking the crates that act on it.
//! - [`files`]: the other files (`run.json`, `task_stats.json`, `checkpoints/latest.json`,
//!   `eval_final.json`) and the lines of the logs (`eval.jsonl`, `metrics.jsonl`) as structs.
//! - [`offline`]: an offline evaluation's records (`offline_eval.jsonl`, `eval_offline.json`), the
//!   prompted model's action error on the held-out tasks' data, kept apart from returns.
//! - [`pack`]: a pack directory's `pack.json` ([`pack::PackRecord`]) and its engine's name.
//! - `display`: what `promptdt eval` prints of an evaluation (`Display` of its files).
//! - [`RunDir`]: where each file lies, with typed readers and writers; errors name the file.

pub mod config;
mod dir;
mod display;
pub mod files;
pub mod offline;
pub mod pack;

pub use dir::{
    append_jsonl, read_json, read_json_opt, read_jsonl, write_json, JsonLines, RunDir, RunDirError,
    SkippedLine, CHECKPOINTS, CONFIG_TOML, EVAL_CSV, EVAL_FINAL_JSON, EVAL_JSONL, LATEST_JSON,
    METRICS_CSV, METRICS_JSONL, OFFLINE_EVAL_CSV, OFFLINE_EVAL_JSONL, OFFLINE_FINAL_JSON, RUN_JSON,
    SUITE_TOML, TASK_STATS_JSON,
};
pub use files::{
    AdaptationStats, DataMismatch, EvalLine, EvalRepeats, FinalEval, Latest, MetricsLine, PackInfo,
    PromptEval, RunInfo, RunStats, TaskResult, TaskStats, TrainState,
};
pub use offline::{
    OfflineEval, OfflineEvalLine, OfflineTaskResult, OFFLINE_MEASURE, OFFLINE_METRIC,
};
