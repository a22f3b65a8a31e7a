//! [`RunDir`]: where each file of a run directory lies, and its typed readers and writers. Every
//! error names the file it concerns (and, in a JSON-lines log, the line).

use serde::de::DeserializeOwned;
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::config::{ConfigError, TrainConfig};
use crate::files::{EvalLine, FinalEval, Latest, MetricsLine, RunInfo, RunStats};

pub const RUN_JSON: &str = "run.json";
pub const CONFIG_TOML: &str = "config.toml";
/// A run on a task suite: the suite file as the run read it (`pdt_envs::family_of_run`).
pub const SUITE_TOML: &str = "suite.toml";
pub const TASK_STATS_JSON: &str = "task_stats.json";
pub const METRICS_JSONL: &str = "metrics.jsonl";
pub const METRICS_CSV: &str = "metrics.csv";
pub const EVAL_JSONL: &str = "eval.jsonl";
pub const EVAL_CSV: &str = "eval.csv";
pub const EVAL_FINAL_JSON: &str = "eval_final.json";
/// The offline evaluations' log (action error on the held-out tasks' data; `crate::offline`).
pub const OFFLINE_EVAL_JSONL: &str = "offline_eval.jsonl";
pub const OFFLINE_EVAL_CSV: &str = "offline_eval.csv";
/// `promptdt eval`'s offline evaluation of the latest checkpoint.
pub const OFFLINE_FINAL_JSON: &str = "eval_offline.json";
pub const CHECKPOINTS: &str = "checkpoints";
pub const LATEST_JSON: &str = "latest.json";

/// What reading or writing a run directory's file can fail with; each variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum RunDirError {
    /// The directory holds no `run.json`.
    #[error("{}: not a run directory (no run.json in it)", path.display())]
    NotARunDir { path: PathBuf },
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A whole-file JSON document is malformed, truncated or lacks a field; serde's message
    /// carries the line and column.
    #[error("{}: {source}", path.display())]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    /// One line of a JSON-lines log is malformed (and is not a truncated last line).
    #[error("{}:{line}:{column}: {message}", path.display())]
    JsonLine {
        path: PathBuf,
        /// 1-based line number in the file.
        line: usize,
        /// 1-based column within that line.
        column: usize,
        message: String,
        #[source]
        source: serde_json::Error,
    },
    /// `config.toml` cannot be read or parsed (the error names the file).
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// Well-formed content that cannot be used.
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
}

impl RunDirError {
    /// Whether the error is a missing file (as opposed to an unreadable or malformed one).
    pub fn is_not_found(&self) -> bool {
        match self {
            RunDirError::Io { source, .. } => source.kind() == std::io::ErrorKind::NotFound,
            RunDirError::Config(ConfigError::Io { source, .. }) => {
                source.kind() == std::io::ErrorKind::NotFound
            }
            _ => false,
        }
    }
}

/// A truncated last line of a JSON-lines log, skipped: what a run killed in the middle of an
/// append leaves behind.
#[derive(Debug, Clone, PartialEq)]
pub struct SkippedLine {
    pub path: PathBuf,
    /// 1-based line number in the file.
    pub line: usize,
    pub message: String,
}

impl std::fmt::Display for SkippedLine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}:{}: skipped a truncated last line (the run was probably stopped while writing \
             it): {}",
            self.path.display(),
            self.line,
            self.message
        )
    }
}

/// The rows of a JSON-lines log, and the truncated last line skipped, if there was one.
#[derive(Debug, Clone, PartialEq)]
pub struct JsonLines<T> {
    pub rows: Vec<T>,
    pub skipped: Option<SkippedLine>,
}

/// A run directory: the paths of its files and their typed readers and writers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RunDir {
    root: PathBuf,
}

impl RunDir {
    /// An existing run directory: one holding `run.json`.
    pub fn open(path: impl Into<PathBuf>) -> Result<Self, RunDirError> {
        let root = path.into();
        if !root.join(RUN_JSON).is_file() {
            return Err(RunDirError::NotARunDir { path: root });
        }
        Ok(Self { root })
    }

    /// The run directory at `path`, which may not exist yet (a run being created, or a directory
    /// whose files are checked one by one).
    pub fn at(path: impl Into<PathBuf>) -> Self {
        Self { root: path.into() }
    }

    /// Whether `path` is a run directory (holds `run.json`).
    pub fn is_run_dir(path: &Path) -> bool {
        path.join(RUN_JSON).is_file()
    }

    pub fn path(&self) -> &Path {
        &self.root
    }

    pub fn info_path(&self) -> PathBuf {
        self.root.join(RUN_JSON)
    }

    pub fn config_path(&self) -> PathBuf {
        self.root.join(CONFIG_TOML)
    }

    /// The run's copy of its task suite file (runs on a suite only).
    pub fn suite_path(&self) -> PathBuf {
        self.root.join(SUITE_TOML)
    }

    pub fn stats_path(&self) -> PathBuf {
        self.root.join(TASK_STATS_JSON)
    }

    pub fn metrics_path(&self) -> PathBuf {
        self.root.join(METRICS_JSONL)
    }

    pub fn metrics_csv_path(&self) -> PathBuf {
        self.root.join(METRICS_CSV)
    }

    pub fn eval_path(&self) -> PathBuf {
        self.root.join(EVAL_JSONL)
    }

    pub fn eval_csv_path(&self) -> PathBuf {
        self.root.join(EVAL_CSV)
    }

    pub fn final_eval_path(&self) -> PathBuf {
        self.root.join(EVAL_FINAL_JSON)
    }

    pub fn offline_eval_path(&self) -> PathBuf {
        self.root.join(OFFLINE_EVAL_JSONL)
    }

    pub fn offline_eval_csv_path(&self) -> PathBuf {
        self.root.join(OFFLINE_EVAL_CSV)
    }

    pub fn offline_final_path(&self) -> PathBuf {
        self.root.join(OFFLINE_FINAL_JSON)
    }

    pub fn checkpoints_dir(&self) -> PathBuf {
        self.root.join(CHECKPOINTS)
    }

    pub fn latest_path(&self) -> PathBuf {
        self.checkpoints_dir().join(LATEST_JSON)
    }

    /// A file of `checkpoints/` by name (the names [`Latest`] records).
    pub fn checkpoint_file(&self, name: &str) -> PathBuf {
        self.checkpoints_dir().join(name)
    }

    /// The training state of the checkpoint of `step` (`checkpoints/state_<step>.json`).
    pub fn state_json_path(&self, step: u64) -> PathBuf {
        self.checkpoints_dir().join(format!("state_{step}.json"))
    }

    /// `run.json`.
    pub fn info(&self) -> Result<RunInfo, RunDirError> {
        read_json(&self.info_path())
    }

    /// `config.toml`, parsed (not validated).
    pub fn config(&self) -> Result<TrainConfig, RunDirError> {
        Ok(TrainConfig::from_file(&self.config_path())?)
    }

    /// `task_stats.json`.
    pub fn stats(&self) -> Result<RunStats, RunDirError> {
        read_json(&self.stats_path())
    }

    /// `checkpoints/latest.json`, checked to name its own step's weights; `None` before the first
    /// checkpoint.
    pub fn latest(&self) -> Result<Option<Latest>, RunDirError> {
        let path = self.latest_path();
        let Some(latest) = read_json_opt::<Latest>(&path)? else { return Ok(None) };
        latest.check().map_err(|message| RunDirError::Invalid { path, message })?;
        Ok(Some(latest))
    }

    /// `eval_final.json`; `None` when the run was not evaluated with `promptdt eval`.
    pub fn final_eval(&self) -> Result<Option<FinalEval>, RunDirError> {
        read_json_opt(&self.final_eval_path())
    }

    /// `eval.jsonl`; `None` when it does not exist (as opposed to existing but empty).
    pub fn eval_lines(&self) -> Result<Option<JsonLines<EvalLine>>, RunDirError> {
        read_jsonl(&self.eval_path())
    }

    /// `offline_eval.jsonl`; `None` when the run made no offline evaluation (every run before
    /// them, and every run with an environment).
    pub fn offline_eval_lines(
        &self,
    ) -> Result<Option<JsonLines<crate::offline::OfflineEvalLine>>, RunDirError> {
        read_jsonl(&self.offline_eval_path())
    }

    /// `eval_offline.json`; `None` when the run was not evaluated offline by `promptdt eval`.
    pub fn offline_final(&self) -> Result<Option<crate::offline::OfflineEval>, RunDirError> {
        read_json_opt(&self.offline_final_path())
    }

    pub fn write_offline_final(
        &self,
        eval: &crate::offline::OfflineEval,
    ) -> Result<(), RunDirError> {
        write_json(&self.offline_final_path(), eval)
    }

    /// `metrics.jsonl`; `None` when it does not exist.
    pub fn metrics(&self) -> Result<Option<JsonLines<MetricsLine>>, RunDirError> {
        read_jsonl(&self.metrics_path())
    }

    /// Creates the directory (and its parents) if needed.
    pub fn create_dir(&self) -> Result<(), RunDirError> {
        std::fs::create_dir_all(&self.root).map_err(io_err(&self.root))
    }

    pub fn write_info(&self, info: &RunInfo) -> Result<(), RunDirError> {
        write_json(&self.info_path(), info)
    }

    /// `config.toml` as [`TrainConfig::to_toml`] writes it.
    pub fn write_config(&self, config: &TrainConfig) -> Result<(), RunDirError> {
        let text = config.to_toml()?;
        let path = self.config_path();
        pdt_base::fs::write_atomic(&path, text.as_bytes()).map_err(io_err(&path))
    }

    pub fn write_stats(&self, stats: &RunStats) -> Result<(), RunDirError> {
        write_json(&self.stats_path(), stats)
    }

    /// `checkpoints/latest.json`: the commit point of a checkpoint, so written last.
    pub fn write_latest(&self, latest: &Latest) -> Result<(), RunDirError> {
        write_json(&self.latest_path(), latest)
    }

    pub fn write_final_eval(&self, eval: &FinalEval) -> Result<(), RunDirError> {
        write_json(&self.final_eval_path(), eval)
    }

    /// `eval_prompt_<strategy>.json`: a final evaluation with a prompt strategy
    /// ([`crate::files::PromptEval`]).
    pub fn prompt_eval_path(&self, strategy: pdt_prompt::PromptStrategyKind) -> PathBuf {
        self.root.join(format!("eval_prompt_{}.json", strategy.name()))
    }

    /// `eval_adapt_<kind>.json`: a final evaluation with an evaluation-time adaptation.
    pub fn adapt_eval_path(&self, kind: crate::config::AdaptKind) -> PathBuf {
        self.root.join(format!("eval_adapt_{}.json", kind.name()))
    }

    pub fn write_prompt_eval(&self, eval: &crate::files::PromptEval) -> Result<(), RunDirError> {
        if !eval.adapt.is_none() {
            return write_json(&self.adapt_eval_path(eval.adapt.kind), eval);
        }
        write_json(&self.prompt_eval_path(eval.prompt_strategy.strategy), eval)
    }

    /// Appends lines to `eval.jsonl` (the CSV beside it is the trainer's log's).
    pub fn append_eval_lines(&self, lines: &[EvalLine]) -> Result<(), RunDirError> {
        append_jsonl(&self.eval_path(), lines)
    }

    /// Appends lines to `metrics.jsonl`.
    pub fn append_metrics(&self, lines: &[MetricsLine]) -> Result<(), RunDirError> {
        append_jsonl(&self.metrics_path(), lines)
    }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RunDirError + '_ {
    move |source| RunDirError::Io { path: path.into(), source }
}

/// Reads and parses a whole-file JSON document.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T, RunDirError> {
    let text = pdt_base::fs::read_text_limited(path, pdt_base::fs::MAX_TEXT_BYTES)
        .map_err(io_err(path))?;
    serde_json::from_str(&text).map_err(|source| RunDirError::Json { path: path.into(), source })
}

/// [`read_json`], `None` when the file does not exist.
pub fn read_json_opt<T: DeserializeOwned>(path: &Path) -> Result<Option<T>, RunDirError> {
    match read_json(path) {
        Err(e) if e.is_not_found() => Ok(None),
        other => other.map(Some),
    }
}

/// Writes `value` as pretty JSON, atomically.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), RunDirError> {
    let text = serde_json::to_string_pretty(value)
        .map_err(|source| RunDirError::Json { path: path.into(), source })?;
    pdt_base::fs::write_atomic(path, text.as_bytes()).map_err(io_err(path))
}

/// Appends one compact JSON line per row (one write, so a kill cuts at most the last line).
pub fn append_jsonl<T: Serialize>(path: &Path, rows: &[T]) -> Result<(), RunDirError> {
    let mut text = String::new();
    for row in rows {
        let line = serde_json::to_string(row)
            .map_err(|source| RunDirError::Json { path: path.into(), source })?;
        text.push_str(&line);
        text.push('\n');
    }
    let mut f =
        std::fs::OpenOptions::new().create(true).append(true).open(path).map_err(io_err(path))?;
    f.write_all(text.as_bytes()).map_err(io_err(path))
}

/// Parses a JSON-lines file; `None` when it does not exist. Blank lines are ignored. A last line
/// that fails to parse and has no terminating newline is what a run killed in the middle of an
/// append leaves behind: it is skipped and returned in [`JsonLines::skipped`]. Any other
/// malformed line is an error naming the file and line.
pub fn read_jsonl<T: DeserializeOwned>(path: &Path) -> Result<Option<JsonLines<T>>, RunDirError> {
    let text = match pdt_base::fs::read_text_limited(path, pdt_base::fs::MAX_TEXT_BYTES) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(RunDirError::Io { path: path.into(), source: e }),
    };
    let unterminated = !text.is_empty() && !text.ends_with('\n');
    let lines: Vec<&str> = text.split('\n').collect();
    let mut out = JsonLines { rows: Vec::with_capacity(lines.len()), skipped: None };
    for (i, line) in lines.iter().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        match serde_json::from_str::<T>(line) {
            Ok(v) => out.rows.push(v),
            // Only the very last piece of an unterminated file can be a cut write.
            Err(source) if unterminated && i + 1 == lines.len() => {
                let message = strip_position(&source);
                out.skipped = Some(SkippedLine { path: path.into(), line: i + 1, message });
            }
            Err(source) => {
                return Err(RunDirError::JsonLine {
                    path: path.into(),
                    line: i + 1,
                    column: source.column(),
                    message: strip_position(&source),
                    source,
                })
            }
        }
    }
    Ok(Some(out))
}

/// serde_json appends " at line L column C" to its messages; within a JSON-lines file that line is
/// always 1 and would contradict the file line number reported, so it is dropped.
fn strip_position(e: &serde_json::Error) -> String {
    let s = e.to_string();
    match s.rfind(" at line ") {
        Some(idx) => s[..idx].to_string(),
        None => s,
    }
}
