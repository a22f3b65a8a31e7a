//! The trainer's bookkeeping of a run directory (`docs/run-directory.md`) over `pdt-rundir`'s typed
//! files: the logs with their CSV mirrors cut back to a checkpoint's line counts, the commit of a
//! checkpoint, the checks of a state file's counts, the directory's lock, and the clean-up of what
//! a killed run left behind.

use crate::error::{io_err, RunError};
use pdt_base::fs::write_atomic;
use pdt_rundir::{read_json, write_json, Latest, TrainState};
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};

/// One row of a log as written: column name to value, in the order of the name (serde_json's map),
/// which every run directory's logs have had.
type Row = serde_json::Map<String, serde_json::Value>;

/// Appends JSON lines (and matching CSV rows) to a log.
pub(crate) struct Log {
    jsonl: PathBuf,
    csv: PathBuf,
    pub(crate) lines: usize,
    /// `time/elapsed_s` of the last kept line (0 for a new log). A resumed run adds its own time to
    /// it, so the column is the training time of the kept iterations, not the time since the last
    /// resume (the time between the last resume point and a kill is not counted: that work is redone).
    pub(crate) elapsed_before: f64,
}

impl Log {
    /// The log `jsonl` (`RunDir::metrics_path`, `eval_path`) with its CSV mirror `csv`, cut back
    /// to its first `keep_lines` lines.
    pub(crate) fn open(jsonl: PathBuf, csv: PathBuf, keep_lines: usize) -> Result<Self, RunError> {
        // Keep exactly the lines the checkpoint knew about: a killed run may have written more.
        // The JSON lines are the record; the CSV is rebuilt from them (a deleted or edited CSV
        // is repaired, with its header).
        let text = match std::fs::read_to_string(&jsonl) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
            Err(e) => return Err(RunError::Io { path: jsonl, source: e }),
        };
        let kept: Vec<&str> = text.lines().take(keep_lines).collect();
        if kept.len() < keep_lines {
            return Err(RunError::Corrupt {
                path: jsonl,
                message: format!(
                    "{} lines, but the checkpoint recorded {keep_lines}: the log was truncated or \
                     deleted. Restore it, or start the run again",
                    kept.len()
                ),
            });
        }
        let mut log =
            Self { jsonl: jsonl.clone(), csv: csv.clone(), lines: 0, elapsed_before: 0.0 };
        let mut rows = Vec::with_capacity(kept.len());
        for (i, line) in kept.iter().enumerate() {
            match serde_json::from_str::<serde_json::Value>(line) {
                Ok(serde_json::Value::Object(m)) => rows.push(m),
                _ => {
                    return Err(RunError::Corrupt {
                        path: jsonl,
                        message: format!("line {} is not a JSON object", i + 1),
                    })
                }
            }
        }
        let (j, c) = log.render(&rows);
        write_atomic(&jsonl, j.as_bytes()).map_err(io_err(&jsonl))?;
        write_atomic(&csv, c.as_bytes()).map_err(io_err(&csv))?;
        log.lines = rows.len();
        log.elapsed_before = rows
            .last()
            .and_then(|r| r.get("time/elapsed_s"))
            .and_then(serde_json::Value::as_f64)
            .unwrap_or(0.0);
        Ok(log)
    }

    /// The JSON lines and CSV rows (with the header when the log is empty) of `rows`.
    fn render(&self, rows: &[Row]) -> (String, String) {
        let (mut j, mut c) = (String::new(), String::new());
        for (i, row) in rows.iter().enumerate() {
            if self.lines + i == 0 {
                let header: Vec<&str> = row.keys().map(String::as_str).collect();
                c.push_str(&header.join(","));
                c.push('\n');
            }
            let values: Vec<String> = row
                .values()
                .map(|v| v.as_str().map_or_else(|| v.to_string(), str::to_string))
                .collect();
            c.push_str(&values.join(","));
            c.push('\n');
            j.push_str(&serde_json::Value::Object(row.clone()).to_string());
            j.push('\n');
        }
        (j, c)
    }

    /// Appends typed lines (`pdt_rundir::MetricsLine`, `EvalLine`). Each is written through
    /// serde_json's map, so its columns come in name order as in every earlier run directory
    /// (and the CSV's header matches the JSON lines).
    pub(crate) fn append<T: Serialize>(&mut self, lines: &[T]) -> Result<(), RunError> {
        let corrupt = |message: String| RunError::Corrupt { path: self.jsonl.clone(), message };
        let mut rows = Vec::with_capacity(lines.len());
        for line in lines {
            match serde_json::to_value(line) {
                Ok(serde_json::Value::Object(row)) => rows.push(row),
                Ok(other) => return Err(corrupt(format!("a log line is not an object: {other}"))),
                Err(e) => return Err(corrupt(e.to_string())),
            }
        }
        let rows = &rows;
        let mut j = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.jsonl)
            .map_err(io_err(&self.jsonl))?;
        let mut c = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.csv)
            .map_err(io_err(&self.csv))?;
        let (text_j, text_c) = self.render(rows);
        c.write_all(text_c.as_bytes()).map_err(io_err(&self.csv))?;
        j.write_all(text_j.as_bytes()).map_err(io_err(&self.jsonl))?;
        self.lines += rows.len();
        Ok(())
    }
}

/// Makes a checkpoint whose files are written the one in force: `latest.json` last, so a crash
/// before it leaves the previous one in force; then what the previous one no longer needs goes.
pub(crate) fn commit_checkpoint(ck: &Path, latest: Latest) -> Result<(), RunError> {
    let previous: Option<Latest> = read_json(&ck.join("latest.json")).ok();
    let step = latest.step;
    write_json(&ck.join("latest.json"), &latest)?;
    // Optimiser moments are only needed to resume: keep the latest ones. Weights are kept at
    // every checkpoint; a resume point's go once a later one is in force.
    if let Some(p) = previous.filter(|p| p.step != step) {
        let _ = std::fs::remove_file(ck.join(&p.state));
        if !p.keep {
            let _ = std::fs::remove_file(ck.join(&p.model));
            let _ = std::fs::remove_file(ck.join(format!("state_{}.json", p.step)));
        }
    }
    Ok(())
}

/// When a run evaluates, for [`check_log_counts`]: how many tasks each evaluation logs, and the
/// intervals (`train.test_eval_interval`, `train.train_eval_interval`; 0: never).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct EvalSchedule {
    pub(crate) test_tasks: usize,
    pub(crate) train_tasks: usize,
    pub(crate) test_eval_interval: u64,
    pub(crate) train_eval_interval: u64,
}

/// A state file's log line counts against what its iteration implies: one metrics line per
/// iteration, and at least one evaluation line per task for each scheduled evaluation (after
/// iteration 1 and every interval after it; the last iteration of each earlier call adds more, so
/// this is a lower bound). A smaller count would truncate the logs on resume: refused, naming both.
pub(crate) fn check_log_counts(
    state_path: &Path,
    state: &TrainState,
    schedule: &EvalSchedule,
) -> Result<(), RunError> {
    let (iteration, metrics_lines, eval_lines) =
        (state.iteration, state.metrics_lines, state.eval_lines);
    let (test_tasks, train_tasks) = (schedule.test_tasks, schedule.train_tasks);
    let corrupt = |message: String| RunError::Corrupt { path: state_path.into(), message };
    if metrics_lines as u64 != iteration {
        return Err(corrupt(format!(
            "metrics_lines = {metrics_lines}, but iteration {iteration} implies {iteration} (one \
             metrics line per iteration); the state file was edited or is corrupt, and resuming \
             would cut metrics.jsonl to its count. Nothing was changed"
        )));
    }
    // Evaluations after iterations 1, 1 + n, ... up to `iteration`.
    let scheduled = |n: u64| if iteration == 0 || n == 0 { 0 } else { (iteration - 1) / n + 1 };
    let t = schedule;
    let least = scheduled(t.test_eval_interval)
        .saturating_mul(test_tasks as u64)
        .saturating_add(scheduled(t.train_eval_interval).saturating_mul(train_tasks as u64));
    if (eval_lines as u64) < least {
        return Err(corrupt(format!(
            "eval_lines = {eval_lines}, but iteration {iteration} implies at least {least} \
             ({test_tasks} test tasks every train.test_eval_interval = {}, {train_tasks} training \
             tasks every train.train_eval_interval = {}); the state file was edited or is \
             corrupt, and resuming would cut eval.jsonl to its count. Nothing was changed",
            t.test_eval_interval, t.train_eval_interval
        )));
    }
    Ok(())
}

/// The temporary name a checkpoint file is written under before its rename: one that
/// `pdt_base::fs::remove_stale_temps` recognises, so a kill mid-write leaves nothing behind.
pub(crate) fn temp_name(name: &str) -> String {
    format!(".{name}.tmp-{}-0", std::process::id())
}

/// What a checkpoint file is, by its name: `step_<N>.safetensors` (weights),
/// `state_<N>.safetensors` (optimiser moments) or `state_<N>.json` (training state).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CheckpointFile {
    Weights,
    Moments,
    State,
}

fn checkpoint_file(name: &str) -> Option<(CheckpointFile, u64)> {
    let (kind, rest) = if let Some(r) = name.strip_prefix("step_") {
        (CheckpointFile::Weights, r.strip_suffix(".safetensors")?)
    } else if let Some(r) = name.strip_prefix("state_") {
        match r.strip_suffix(".safetensors") {
            Some(n) => (CheckpointFile::Moments, n),
            None => (CheckpointFile::State, r.strip_suffix(".json")?),
        }
    } else {
        return None;
    };
    if rest.is_empty() || !rest.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some((kind, rest.parse().ok()?))
}

/// Removes the checkpoint files a killed run left behind, which `latest.json` does not reference:
/// the files of a checkpoint written but never committed (a step beyond the latest), optimiser
/// moments of any other step than the latest (only the latest are needed to resume), a resume
/// point's weights and state whose removal was cut short (`keep: false` in its state file, or a
/// state file without its weights; weights without a state file are kept, no kill leaves those),
/// and the temporary files of the writers of older versions (`.state_<N>.safetensors.tmp`).
/// Without `latest.json` nothing was committed: every checkpoint file goes (training starts from
/// iteration 0 and writes them again, identically). Call it only while owning the run directory.
/// Returns the names removed.
pub(crate) fn remove_orphans(ck: &Path) -> Result<Vec<String>, RunError> {
    let entries = match std::fs::read_dir(ck) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(RunError::Io { path: ck.into(), source: e }),
    };
    let latest_path = ck.join("latest.json");
    let latest: Option<Latest> = if latest_path.exists() {
        // An unreadable latest.json is refused by name when the checkpoint is loaded; until then
        // nothing can be told apart, so nothing is removed.
        match read_json(&latest_path) {
            Ok(l) => Some(l),
            Err(_) => return Ok(Vec::new()),
        }
    } else {
        None
    };
    let mut names = Vec::new();
    for entry in entries {
        let entry = entry.map_err(io_err(ck))?;
        if entry.file_type().map_err(io_err(ck))?.is_file() {
            names.push(entry.file_name().to_string_lossy().into_owned());
        }
    }
    // Whether step n's state file marks it a resume point (`keep: false`); `false` when the file
    // is missing, unreadable or older than the field (such weights are kept).
    let resume_point = |n: u64| -> bool {
        read_json::<TrainState>(&ck.join(format!("state_{n}.json"))).is_ok_and(|s| !s.keep)
    };
    // Decide for every file before removing any (a state file is read to decide on its weights).
    let mut orphans = Vec::new();
    for name in names {
        let legacy_temp = name.starts_with(".step_") || name.starts_with(".state_");
        let orphan = if legacy_temp && name.ends_with(".tmp") {
            true
        } else if let Some((kind, n)) = checkpoint_file(&name) {
            match &latest {
                None => true,
                Some(l) if n == l.step => false,
                Some(l) if n > l.step => true,
                Some(_) => match kind {
                    CheckpointFile::Moments => true,
                    // `commit_checkpoint` removes a resume point's weights before its state
                    // file: a kill between leaves the state file alone.
                    CheckpointFile::Weights => resume_point(n),
                    CheckpointFile::State => {
                        resume_point(n) || !ck.join(format!("step_{n}.safetensors")).is_file()
                    }
                },
            }
        } else {
            false
        };
        if orphan {
            orphans.push(name);
        }
    }
    orphans.sort();
    for name in &orphans {
        let path = ck.join(name);
        std::fs::remove_file(&path).map_err(io_err(&path))?;
    }
    Ok(orphans)
}

/// Takes ownership of a run directory for this process (see `pdt_base::fs::DirLock`).
pub(crate) fn lock_run_dir(dir: &Path) -> Result<pdt_base::fs::DirLock, RunError> {
    pdt_base::fs::DirLock::try_acquire(dir).map_err(|e| {
        if e.kind() == std::io::ErrorKind::WouldBlock {
            RunError::Busy { dir: dir.into(), lock: dir.join(".lock") }
        } else {
            RunError::Io { path: dir.join(".lock"), source: e }
        }
    })
}

pub(crate) fn now_utc() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    format!("unix:{secs}")
}
