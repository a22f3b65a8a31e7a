//! Finding run directories and parsing the files described in `docs/run-directory.md`.
//!
//! Only the fields the report needs are parsed; unknown fields are ignored so that the training
//! side can add keys without breaking reports.

use std::collections::HashSet;
use std::fs;
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Deserializer};

use crate::error::ReportError;

/// `run.json`: the identity of a run.
#[derive(Debug, Clone, Deserialize)]
pub(crate) struct RunInfo {
    #[serde(default)]
    pub name: Option<String>,
    pub method: String,
    pub env: String,
    #[serde(default)]
    pub seed: Option<u64>,
    /// Task split name ("default", "ood", ...). Runs on different splits are never averaged
    /// together, because their test tasks differ.
    #[serde(default)]
    pub split: Option<String>,
}

/// One line of `eval.jsonl`.
#[derive(Debug, Clone, Deserialize)]
pub(crate) struct EvalLine {
    pub iteration: u64,
    pub split: String,
    pub task: String,
    #[serde(default)]
    pub task_index: Option<i64>,
    /// serde_json writes a NaN return (a diverged policy) as `null`; keep it as NaN so the
    /// table shows it instead of the run silently disappearing.
    #[serde(deserialize_with = "f64_or_null")]
    pub return_mean: f64,
}

/// One line of `metrics.jsonl`; only what the per-run summary shows.
#[derive(Debug, Clone, Deserialize)]
pub(crate) struct MetricsLine {
    pub iteration: u64,
    #[serde(default, rename = "train/action_loss")]
    pub action_loss: Option<f64>,
    #[serde(default, rename = "time/elapsed_s")]
    pub elapsed_s: Option<f64>,
}

/// `eval_final.json`, written by `promptdt eval`.
#[derive(Debug, Clone, Deserialize)]
pub(crate) struct EvalFinal {
    #[serde(default)]
    pub iteration: Option<u64>,
    #[serde(default)]
    pub split: Option<String>,
    pub tasks: Vec<FinalTask>,
}

#[derive(Debug, Clone, Deserialize)]
pub(crate) struct FinalTask {
    pub task: String,
    #[serde(default)]
    pub task_index: Option<i64>,
    #[serde(deserialize_with = "f64_or_null")]
    pub return_mean: f64,
}

fn f64_or_null<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// Everything read from one run directory.
#[derive(Debug, Clone)]
pub(crate) struct Run {
    pub dir: PathBuf,
    pub info: RunInfo,
    /// `None` when `eval.jsonl` does not exist (as opposed to existing but empty).
    pub evals: Option<Vec<EvalLine>>,
    pub final_eval: Option<EvalFinal>,
    pub metrics: Option<Vec<MetricsLine>>,
}

impl Run {
    /// The label used in tables and plot titles; runs on a non-default split get it appended
    /// so they form their own group.
    pub fn env_label(&self) -> String {
        match self.info.split.as_deref() {
            None | Some("") | Some("default") => self.info.env.clone(),
            Some(split) => format!("{} ({split})", self.info.env),
        }
    }
}

/// Expands the user's paths into run directories (directories holding `run.json`), in a stable
/// order, without duplicates.
pub(crate) fn discover(paths: &[PathBuf]) -> Result<Vec<PathBuf>, ReportError> {
    let mut found = Vec::new();
    // Canonical paths, so that `runs/` and `runs/a/` given together do not count run `a` twice.
    let mut seen_runs = HashSet::new();
    for path in paths {
        let meta = fs::metadata(path).map_err(|e| ReportError::io(path, e))?;
        if meta.is_file() {
            if path.file_name().is_some_and(|n| n == "run.json") {
                let dir = match path.parent() {
                    Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
                    _ => PathBuf::from("."),
                };
                push_unique(&dir, &mut found, &mut seen_runs)?;
                continue;
            }
            return Err(ReportError::NotARunDir { path: path.clone() });
        }
        // Per top-level path, so that a symlink loop cannot make the walk run forever.
        let mut seen_dirs = HashSet::new();
        if walk(path, &mut found, &mut seen_runs, &mut seen_dirs)? == 0 {
            return Err(ReportError::NoRunsFound { path: path.clone() });
        }
    }
    Ok(found)
}

fn is_run_dir(dir: &Path) -> bool {
    dir.join("run.json").is_file()
}

fn push_unique(
    dir: &Path,
    found: &mut Vec<PathBuf>,
    seen: &mut HashSet<PathBuf>,
) -> Result<(), ReportError> {
    let canon = fs::canonicalize(dir).map_err(|e| ReportError::io(dir, e))?;
    if seen.insert(canon) {
        found.push(dir.to_path_buf());
    }
    Ok(())
}

/// Returns the number of run directories met, counting ones already found via another path.
fn walk(
    dir: &Path,
    found: &mut Vec<PathBuf>,
    seen_runs: &mut HashSet<PathBuf>,
    seen_dirs: &mut HashSet<PathBuf>,
) -> Result<usize, ReportError> {
    let canon = fs::canonicalize(dir).map_err(|e| ReportError::io(dir, e))?;
    if !seen_dirs.insert(canon) {
        return Ok(0);
    }
    if is_run_dir(dir) {
        // A run directory's subfolders (checkpoints/) never hold further runs.
        push_unique(dir, found, seen_runs)?;
        return Ok(1);
    }
    let entries = fs::read_dir(dir).map_err(|e| ReportError::io(dir, e))?;
    let mut subdirs = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| ReportError::io(dir, e))?;
        let path = entry.path();
        // metadata() follows symlinks, so linked run folders are found too.
        if fs::metadata(&path).is_ok_and(|m| m.is_dir()) {
            subdirs.push(path);
        }
    }
    // Sorted so that the report (and its warnings) do not depend on directory order.
    subdirs.sort();
    let mut runs = 0;
    for sub in subdirs {
        runs += walk(&sub, found, seen_runs, seen_dirs)?;
    }
    Ok(runs)
}

/// Loads one run directory. Missing optional files are `None`; malformed files are errors,
/// except for a truncated last `.jsonl` line, which is reported in `warnings` and skipped.
pub(crate) fn load_run(dir: &Path, warnings: &mut Vec<String>) -> Result<Run, ReportError> {
    let run_json = dir.join("run.json");
    let info: RunInfo =
        read_json(&run_json)?.ok_or_else(|| ReportError::NotARunDir { path: dir.to_path_buf() })?;
    for (field, value) in [("method", &info.method), ("env", &info.env)] {
        if value.trim().is_empty() {
            return Err(ReportError::Invalid {
                path: run_json,
                message: format!("field `{field}` is empty"),
            });
        }
    }
    let evals = read_jsonl::<EvalLine>(&dir.join("eval.jsonl"), warnings)?;
    let metrics = read_jsonl::<MetricsLine>(&dir.join("metrics.jsonl"), warnings)?;
    let final_eval = read_json::<EvalFinal>(&dir.join("eval_final.json"))?;
    Ok(Run { dir: dir.to_path_buf(), info, evals, final_eval, metrics })
}

fn read_to_string_opt(path: &Path) -> Result<Option<String>, ReportError> {
    match pdt_base::fs::read_text_limited(path, pdt_base::fs::MAX_TEXT_BYTES) {
        Ok(s) => Ok(Some(s)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(ReportError::io(path, e)),
    }
}

fn read_json<T: DeserializeOwned>(path: &Path) -> Result<Option<T>, ReportError> {
    let Some(text) = read_to_string_opt(path)? else {
        return Ok(None);
    };
    serde_json::from_str(&text)
        .map(Some)
        .map_err(|source| ReportError::Json { path: path.to_path_buf(), source })
}

/// Parses a JSON-lines file. Blank lines are ignored. A last line that fails to parse and has
/// no terminating newline is what a run killed in the middle of an append leaves behind: it is
/// skipped with a warning. Any other malformed line is an error naming the file and line.
pub(crate) fn read_jsonl<T: DeserializeOwned>(
    path: &Path,
    warnings: &mut Vec<String>,
) -> Result<Option<Vec<T>>, ReportError> {
    let Some(text) = read_to_string_opt(path)? else {
        return Ok(None);
    };
    let unterminated = !text.is_empty() && !text.ends_with('\n');
    let lines: Vec<&str> = text.split('\n').collect();
    // Index of the last non-blank line: the only one allowed to be a truncated write.
    let last_content = lines.iter().rposition(|l| !l.trim().is_empty());
    let mut out = Vec::with_capacity(lines.len());
    for (i, line) in lines.iter().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        match serde_json::from_str::<T>(line) {
            Ok(v) => out.push(v),
            Err(source) => {
                let is_last = Some(i) == last_content && i + 1 == lines.len();
                if is_last && unterminated {
                    warnings.push(format!(
                        "{}:{}: skipped a truncated last line (the run was probably stopped while writing it): {}",
                        path.display(),
                        i + 1,
                        strip_position(&source)
                    ));
                    continue;
                }
                return Err(ReportError::JsonLine {
                    path: path.to_path_buf(),
                    line: i + 1,
                    column: source.column(),
                    message: strip_position(&source),
                    source,
                });
            }
        }
    }
    Ok(Some(out))
}

/// serde_json appends " at line L column C" to its messages; within a JSONL file that line is
/// always 1 and would contradict the file line number we report, so drop it.
fn strip_position(e: &serde_json::Error) -> String {
    let s = e.to_string();
    match s.rfind(" at line ") {
        Some(idx) => s[..idx].to_string(),
        None => s,
    }
}
