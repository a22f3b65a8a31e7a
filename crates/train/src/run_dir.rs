//! The run directory's records and their readers and writers (`docs/run-directory.md`): `run.json`,
//! `task_stats.json`, the checkpoints' `latest.json` and state files, the logs, `eval_final.json`,
//! the directory's lock, and the clean-up of what a killed run left behind. Gathered here so that
//! they can be swapped for `pdt-rundir`'s typed records in one place.

use crate::config::{compact, MAX_STATE_STAT};
use crate::error::{io_err, RunError};
use pdt_eval::TaskResult;
use pdt_model::checkpoint::write_atomic;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The run's identity (`run.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunInfo {
    pub name: String,
    pub method: String,
    pub env: String,
    pub seed: u64,
    pub split: String,
    pub created: String,
    pub promptdt_version: String,
    /// The `metrics.jsonl` column of the training loss (`train/action_loss` for the Prompt-DT
    /// variants, `train/policy_outer_loss` for MACAW). Absent in runs written before it was
    /// recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_metric: Option<String>,
}

/// What evaluation needs besides weights (`task_stats.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskStats {
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

impl TaskStats {
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
    pub(crate) fn check_same_as(&self, recorded: &TaskStats) -> Result<(), String> {
        let fp = |now: &str, then: &str, which: &str| {
            if !then.is_empty() && now != then {
                Err(format!(
                    "the {which} data differ from what the run trained on ({then}, now {now})"
                ))
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
            return Err("the state statistics, tasks or return settings recomputed from the \
                        configuration and data differ from those the run recorded"
                .into());
        }
        Ok(())
    }
}

/// The commit point of a checkpoint (`checkpoints/latest.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Latest {
    pub(crate) step: u64,
    pub(crate) iteration: u64,
    pub(crate) model: String,
    pub(crate) state: String,
    /// `false` for a resume point between checkpoints (`train.resume_interval`): its weights are
    /// removed once a later checkpoint is in force. Absent in runs written before the option.
    #[serde(default = "keep_default")]
    pub(crate) keep: bool,
}

/// `|x| <= bound`, false for NaN.
pub(crate) fn within(x: f64, bound: f64) -> bool {
    x.abs() <= bound
}

fn keep_default() -> bool {
    true
}

/// Training state besides weights and moments (`checkpoints/state_<N>.json`). The fields are in
/// the order the files of earlier versions have them, so that a run's files stay byte-identical.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct TrainState {
    /// The method whose state this is, for the methods that record it (MACAW: `"macaw"`; absent
    /// for the Prompt-DT variants, whose files never had it): the learner's `state_tag`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) method: Option<String>,
    pub(crate) iteration: u64,
    pub(crate) step: u64,
    /// Position of the batch-sampling RNG (a u128, as a decimal string).
    pub(crate) batch_rng_word_pos: String,
    /// The optimiser steps taken, in the learner's own layout (opaque to the loop; each learner
    /// writes and checks its own: `Learner::save`).
    pub(crate) adam_steps: serde_json::Value,
    pub(crate) metrics_lines: usize,
    pub(crate) eval_lines: usize,
    /// As `latest.json`'s `keep`: `false` for a resume point, whose files go once a later one is
    /// in force. Recorded here too, so a removal cut short by a kill is finished on the next start
    /// (`remove_orphans`). Absent in runs written before it was recorded (then kept).
    #[serde(default = "keep_default")]
    pub(crate) keep: bool,
}

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
    pub(crate) fn open(dir: &Path, stem: &str, keep_lines: usize) -> Result<Self, RunError> {
        let (jsonl, csv) = (dir.join(format!("{stem}.jsonl")), dir.join(format!("{stem}.csv")));
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
    fn render(&self, rows: &[serde_json::Map<String, serde_json::Value>]) -> (String, String) {
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

    pub(crate) fn append(
        &mut self,
        rows: &[serde_json::Map<String, serde_json::Value>],
    ) -> Result<(), RunError> {
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

pub(crate) fn eval_rows(
    results: &[TaskResult],
    iteration: u64,
    step: u64,
    split: &str,
    target: f32,
) -> Vec<serde_json::Map<String, serde_json::Value>> {
    results
        .iter()
        .map(|r| {
            let v = serde_json::json!({
                "iteration": iteration, "step": step, "split": split, "task": r.task, "task_index": r.task_index,
                "return_mean": r.return_mean, "return_std": r.return_std, "length_mean": r.length_mean,
                "episodes": r.episodes, "target_return": target,
            });
            let mut row = v.as_object().cloned().unwrap_or_default();
            // Only families with a success criterion (Meta-World) have the column.
            if let Some(rate) = r.success_rate {
                row.insert("success_rate".into(), rate.into());
            }
            row
        })
        .collect()
}

pub(crate) fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), RunError> {
    let text = serde_json::to_string_pretty(value)
        .map_err(|e| RunError::Corrupt { path: path.into(), message: e.to_string() })?;
    write_atomic(path, text.as_bytes()).map_err(io_err(path))
}

pub(crate) fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, RunError> {
    let text = pdt_base::fs::read_text_limited(path, pdt_base::fs::MAX_TEXT_BYTES)
        .map_err(io_err(path))?;
    serde_json::from_str(&text)
        .map_err(|e| RunError::Corrupt { path: path.into(), message: e.to_string() })
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
        let state = ck.join(format!("state_{n}.json"));
        pdt_base::fs::read_text_limited(&state, pdt_base::fs::MAX_TEXT_BYTES)
            .ok()
            .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
            .and_then(|v| v.get("keep").and_then(serde_json::Value::as_bool))
            .is_some_and(|keep| !keep)
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
            RunError::Invalid(format!(
                "{} is in use by another promptdt process (it holds {}); wait for it to finish, \
                 or pick another --out",
                dir.display(),
                dir.join(".lock").display()
            ))
        } else {
            RunError::Io { path: dir.join(".lock"), source: e }
        }
    })
}

/// Reads a run's `task_stats.json`, saying what a missing one means, and checks its values (a
/// hand-edited or corrupt file must not normalise states by NaN or 0).
pub(crate) fn read_task_stats(dir: &Path) -> Result<TaskStats, RunError> {
    let path = dir.join("task_stats.json");
    if !path.exists() {
        let why = if dir.join("checkpoints").join("latest.json").exists() {
            "but the run has a checkpoint: it cannot be recreated from today's data without \
             defeating the check that the data did not change. Restore it from a copy of the run, \
             or delete the run"
        } else {
            "the run directory was interrupted while being created (killed before writing it); \
             `promptdt train --resume` recreates it and starts the run, or delete the directory"
        };
        return Err(RunError::Invalid(format!("{} is missing, {why}", path.display())));
    }
    let stats: TaskStats = read_json(&path)?;
    stats.check().map_err(|message| RunError::Corrupt { path, message })?;
    Ok(stats)
}

pub(crate) fn now_utc() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    format!("unix:{secs}")
}

/// The latest checkpoint of the run in `dir` (its weights must be the ones of its step).
pub(crate) fn latest_checkpoint(dir: &Path) -> Result<Latest, RunError> {
    let ck = dir.join("checkpoints");
    let latest: Latest = read_json(&ck.join("latest.json")).map_err(|e| match e {
        RunError::Io { .. } => {
            RunError::Invalid(format!("{}: no checkpoint yet (train first)", dir.display()))
        }
        other => other,
    })?;
    if latest.model != format!("step_{}.safetensors", latest.step) {
        return Err(RunError::Corrupt {
            path: ck.join("latest.json"),
            message: format!("names weights `{}` for step {}", latest.model, latest.step),
        });
    }
    Ok(latest)
}

/// The final evaluation of a run's latest checkpoint (`promptdt eval`), written to `eval_final.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinalEval {
    pub iteration: u64,
    pub step: u64,
    pub checkpoint: String,
    pub split: String,
    pub tasks: Vec<TaskResult>,
    pub mean_return: f64,
    /// MACAW runs: the test-time adaptation used.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptation: Option<String>,
}
