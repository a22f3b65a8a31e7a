//! Finding run directories and reading them through `pdt_rundir` (the run directory's typed
//! files, `docs/run-directory.md`).

use std::collections::HashSet;
use std::fs;
use std::path::{Path, PathBuf};

use pdt_rundir::{
    EvalLine, FinalEval, JsonLines, MetricsLine, OfflineEval, OfflineEvalLine, RunDir, RunDirError,
    RunInfo,
};

use crate::error::ReportError;

/// Everything read from one run directory.
#[derive(Debug, Clone)]
pub(crate) struct Run {
    pub dir: PathBuf,
    pub info: RunInfo,
    /// `None` when `eval.jsonl` does not exist (as opposed to existing but empty).
    pub evals: Option<Vec<EvalLine>>,
    pub final_eval: Option<FinalEval>,
    pub metrics: Option<Vec<MetricsLine>>,
    /// `offline_eval.jsonl` (a run with no environment: action errors, never returns).
    pub offline_evals: Option<Vec<OfflineEvalLine>>,
    /// `eval_offline.json`.
    pub offline_final: Option<OfflineEval>,
}

impl Run {
    /// The label used in tables and plot titles; runs on a non-default split get it appended
    /// so they form their own group.
    pub fn env_label(&self) -> String {
        match self.info.task_split.as_str() {
            "" | "default" => self.info.env.clone(),
            split => format!("{} ({split})", self.info.env),
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
    RunDir::is_run_dir(dir)
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
    let run = RunDir::open(dir).map_err(|_| ReportError::NotARunDir { path: dir.to_path_buf() })?;
    let info = run.info()?;
    for (field, value) in [("method", &info.method), ("env", &info.env)] {
        if value.trim().is_empty() {
            return Err(ReportError::Invalid {
                path: run.info_path(),
                message: format!("field `{field}` is empty"),
            });
        }
    }
    let evals = rows(run.eval_lines()?, warnings);
    let metrics = rows(run.metrics()?, warnings);
    let final_eval = run.final_eval()?;
    let offline_evals = rows(run.offline_eval_lines()?, warnings);
    let offline_final = run.offline_final()?;
    Ok(Run {
        dir: dir.to_path_buf(),
        info,
        evals,
        final_eval,
        metrics,
        offline_evals,
        offline_final,
    })
}

/// The rows of a log, its skipped truncated last line (a kill's) reported in `warnings`.
fn rows<T>(lines: Option<JsonLines<T>>, warnings: &mut Vec<String>) -> Option<Vec<T>> {
    lines.map(|l| {
        if let Some(skipped) = l.skipped {
            warnings.push(skipped.to_string());
        }
        l.rows
    })
}

impl From<RunDirError> for ReportError {
    fn from(e: RunDirError) -> Self {
        match e {
            RunDirError::Io { path, source } => ReportError::Io { path, source },
            RunDirError::Json { path, source } => ReportError::Json { path, source },
            RunDirError::JsonLine { path, line, column, message, source } => {
                ReportError::JsonLine { path, line, column, message, source }
            }
            RunDirError::NotARunDir { path } => ReportError::NotARunDir { path },
            RunDirError::Invalid { path, message } => ReportError::Invalid { path, message },
            // The report reads no config.toml; a message names the file all the same.
            RunDirError::Config(c) => {
                ReportError::Invalid { path: PathBuf::new(), message: c.to_string() }
            }
        }
    }
}
