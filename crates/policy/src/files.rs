//! The run-directory files a policy reads: `config.toml` (with this invocation's device and data
//! place), `task_stats.json` and `checkpoints/latest.json`.
//!
//! Minimal private readers until the typed `RunDir` readers of `pdt-rundir` replace them.

use crate::data::within;
use crate::PolicyError;
use pdt_rundir::config::{compact, DeviceSpec, TrainConfig, MAX_STATE_STAT};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

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
    #[serde(default)]
    pub train_data_fingerprint: String,
    #[serde(default)]
    pub test_data_fingerprint: String,
}

impl TaskStats {
    /// The values a policy can act with (as `pdt_train::run::TaskStats::check`).
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
    pub fn check_same_as(&self, recorded: &TaskStats) -> Result<(), String> {
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

/// The commit point of a checkpoint (`checkpoints/latest.json`): the fields a policy reads.
#[derive(Debug, Clone, Deserialize)]
pub(crate) struct Latest {
    pub(crate) step: u64,
    pub(crate) iteration: u64,
    pub(crate) model: String,
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, PolicyError> {
    let text = pdt_base::fs::read_text_limited(path, pdt_base::fs::MAX_TEXT_BYTES)
        .map_err(|source| PolicyError::Io { path: path.into(), source })?;
    serde_json::from_str(&text)
        .map_err(|e| PolicyError::Corrupt { path: path.into(), message: e.to_string() })
}

/// A run's configuration, for acting with it: its `config.toml` with this invocation's device and
/// the place its data moved to.
pub(crate) fn run_config(
    dir: &Path,
    device: Option<DeviceSpec>,
    data: Option<&Path>,
) -> Result<TrainConfig, PolicyError> {
    let config = dir.join("config.toml");
    if !config.is_file() {
        return Err(PolicyError::NotARunDir(dir.into()));
    }
    let mut cfg = TrainConfig::from_file(&config)?;
    if let Some(d) = device {
        cfg.run.device = d;
    }
    if let Some(d) = data {
        cfg.data.dir = std::path::absolute(d).unwrap_or_else(|_| d.to_path_buf());
    }
    cfg.validate()?;
    Ok(cfg)
}

/// Reads a run's `task_stats.json`, saying what a missing one means, and checks its values (a
/// hand-edited or corrupt file must not normalise states by NaN or 0).
pub(crate) fn read_task_stats(dir: &Path) -> Result<TaskStats, PolicyError> {
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
        return Err(PolicyError::Invalid(format!("{} is missing, {why}", path.display())));
    }
    let stats: TaskStats = read_json(&path)?;
    stats.check().map_err(|message| PolicyError::Corrupt { path, message })?;
    Ok(stats)
}

/// The latest checkpoint of the run in `dir` (its weights must be the ones of its step).
pub(crate) fn latest_checkpoint(dir: &Path) -> Result<Latest, PolicyError> {
    let ck = dir.join("checkpoints");
    let latest: Latest = read_json(&ck.join("latest.json")).map_err(|e| match e {
        PolicyError::Io { .. } => PolicyError::NoCheckpoint(dir.into()),
        other => other,
    })?;
    if latest.model != format!("step_{}.safetensors", latest.step) {
        return Err(PolicyError::Corrupt {
            path: ck.join("latest.json"),
            message: format!("names weights `{}` for step {}", latest.model, latest.step),
        });
    }
    Ok(latest)
}

/// The weights file `latest` names.
pub(crate) fn weights(dir: &Path, latest: &Latest) -> PathBuf {
    dir.join("checkpoints").join(&latest.model)
}
