//! The run-directory files that using a finished or interrupted run reads, through `pdt-rundir`'s
//! typed readers: `config.toml` (with this invocation's device and data place), `task_stats.json`
//! and `checkpoints/latest.json`, each with what a missing or bad one means. An acting policy, the
//! trainer's final evaluation and its resume read them here, so all three refuse alike.

use crate::LoadError;
use pdt_base::device::DeviceSpec;
use pdt_rundir::config::TrainConfig;
use pdt_rundir::{Latest, RunDir, RunDirError, RunStats};
use std::path::Path;

/// A run's configuration, for acting with it: its `config.toml` with this invocation's device and
/// the place its data moved to.
pub fn run_config(
    dir: &RunDir,
    device: Option<DeviceSpec>,
    data: Option<&Path>,
) -> Result<TrainConfig, LoadError> {
    if !dir.config_path().is_file() {
        return Err(LoadError::NotARunDir(dir.path().into()));
    }
    let mut cfg = dir.config()?;
    if let Some(d) = device {
        cfg.run.device = d;
    }
    if let Some(d) = data {
        // Absolute against the current directory (not resolving symlinks).
        cfg.data.dir = std::path::absolute(d).unwrap_or_else(|_| d.to_path_buf());
    }
    cfg.validate()?;
    Ok(cfg)
}

/// Reads a run's `task_stats.json`, saying what a missing one means, and checks its values (a
/// hand-edited or corrupt file must not normalise states by NaN or 0).
pub fn read_stats(dir: &RunDir) -> Result<RunStats, LoadError> {
    let path = dir.stats_path();
    if !path.exists() {
        let why = if dir.latest_path().exists() {
            "but the run has a checkpoint: it cannot be recreated from today's data without \
             defeating the check that the data did not change. Restore it from a copy of the run, \
             or delete the run"
        } else {
            "the run directory was interrupted while being created (killed before writing it); \
             `promptdt train --resume` recreates it and starts the run, or delete the directory"
        };
        return Err(LoadError::Invalid(format!("{} is missing, {why}", path.display())));
    }
    let stats = dir.stats()?;
    stats.check().map_err(|message| LoadError::Corrupt { path, message })?;
    Ok(stats)
}

/// The latest checkpoint of the run (its weights must be the ones of its step).
pub fn latest_checkpoint(dir: &RunDir) -> Result<Latest, LoadError> {
    match dir.latest() {
        Ok(Some(latest)) => Ok(latest),
        Ok(None) | Err(RunDirError::Io { .. }) => Err(LoadError::NoCheckpoint(dir.path().into())),
        Err(e) => Err(e.into()),
    }
}

/// What the run whose `checkpoints/` holds `weights` says of its model, for `model forward` of a
/// run's checkpoint (the file's own record of its number of heads cannot be checked against its
/// shapes; the run's configuration can be); `None` for a file outside a run directory.
pub fn run_architecture_of(
    weights: &Path,
) -> Result<Option<pdt_model::forward_file::RunArchitecture>, LoadError> {
    let Some(checkpoints) = weights.parent() else { return Ok(None) };
    if checkpoints.file_name() != Some("checkpoints".as_ref()) {
        return Ok(None);
    }
    let dir = RunDir::at(checkpoints.parent().unwrap_or(Path::new("")));
    if !dir.config_path().is_file() {
        return Ok(None);
    }
    let m = dir.config()?.model;
    Ok(Some(pdt_model::forward_file::RunArchitecture {
        source: dir.config_path(),
        fields: vec![
            ("hidden_size", m.hidden_size),
            ("n_layer", m.n_layer),
            ("n_head", m.n_head),
            ("n_inner", m.n_inner),
            ("max_ep_len", m.max_ep_len),
            ("n_positions", m.n_positions),
        ],
    }))
}
