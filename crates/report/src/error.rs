//! Typed errors of `pdt-report`. Every variant that concerns a file names it, and a malformed
//! line of a `.jsonl` file is named by its 1-based line number, so a researcher can open the
//! exact spot in an editor.

use std::path::PathBuf;

/// Everything that can make [`crate::run`] or [`crate::dataset_report`] fail.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// `ReportConfig::runs` was empty.
    #[error("no run directories given")]
    NoInput,

    /// Reading, listing or writing a file or directory failed.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// A path given in `ReportConfig::runs` is a directory with no `run.json` in it or below it.
    #[error("{}: no run.json found in this directory or below it", path.display())]
    NoRunsFound { path: PathBuf },

    /// A path given in `ReportConfig::runs` is a file other than a `run.json`.
    #[error("{}: not a run directory (expected a directory containing run.json, or a parent of such directories)", path.display())]
    NotARunDir { path: PathBuf },

    /// A whole-file JSON document (`run.json`, `eval_final.json`) is malformed or lacks a
    /// required field; serde's message carries the line and column.
    #[error("{}: {source}", path.display())]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },

    /// One line of a `.jsonl` file is malformed (and is not a truncated last line, which is
    /// only warned about).
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

    /// Well-formed JSON whose content cannot be used (e.g. an empty `method`).
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },

    /// No run at all had a test evaluation, so there is nothing to tabulate or plot. Each entry
    /// says which run lacked what.
    #[error("no run has test-task evaluations, nothing to report:\n  {}", details.join("\n  "))]
    NoEvalData { details: Vec<String> },

    /// The embedded font could not be registered with plotters.
    #[error("the embedded plot font could not be loaded: {0}")]
    Font(String),

    /// plotters failed while drawing a figure; `figure` says which (e.g. "the learning curves
    /// of cheetah_vel").
    #[error("drawing {figure}: {message}")]
    Plot { figure: String, message: String },

    /// A directory given to [`crate::dataset_report`] does not exist or is not a directory.
    #[error("{}: not a directory", path.display())]
    NotADirectory { path: PathBuf },

    /// A dataset directory given to [`crate::dataset_report`] holds no
    /// `{{env}}-{{task}}-{{mode}}.safetensors` or `.pkl` file, so there is no family to report on.
    #[error("{}: no data files ({{env}}-{{task}}-{{mode}}.safetensors or .pkl) in this directory", path.display())]
    NoDataFiles { path: PathBuf },

    /// A data file could not be read (missing, truncated, malformed, unreadable).
    #[error("{}", data_message(path, source))]
    Data {
        path: PathBuf,
        #[source]
        source: pdt_data::DataError,
    },

    /// Encoding a rendered bitmap as PNG failed.
    #[error("{}: encoding PNG: {source}", path.display())]
    Png {
        path: PathBuf,
        #[source]
        source: png::EncodingError,
    },
}

/// pdt-data's errors usually name the file already; say it once, and add it where they do not
/// (e.g. a shape error).
fn data_message(path: &std::path::Path, source: &pdt_data::DataError) -> String {
    let text = source.to_string();
    let shown = path.display().to_string();
    if text.contains(&shown) {
        text
    } else {
        format!("{shown}: {text}")
    }
}

impl ReportError {
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        ReportError::Io { path: path.into(), source }
    }
}
