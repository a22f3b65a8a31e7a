//! Reading: finding the data files of a directory and recomputing their episode returns.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

use pdt_data::inspect::natural_cmp;
use pdt_data::native::{self, FILE_EXTENSION};
use pdt_data::reference::{load_pickle, ReferenceOptions};
use pdt_data::TaskDataset;

use super::{ReferenceReturn, ReturnStat};
use crate::error::ReportError;

/// (env, task index, mode) of a data file.
pub(super) type FileKey = (String, usize, String);

/// The data files directly in `dir`, keyed by what they hold. A native file's metadata is
/// authoritative over its name (docs/data-format.md); a pickle has only its name. When two files
/// hold the same (env, task, mode), the `.safetensors` wins, as with the loader's `auto` format.
pub(super) fn scan_dir(
    dir: &Path,
    warnings: &mut Vec<String>,
) -> Result<BTreeMap<FileKey, PathBuf>, ReportError> {
    let meta = fs::metadata(dir).map_err(|e| ReportError::io(dir, e))?;
    if !meta.is_dir() {
        return Err(ReportError::NotADirectory { path: dir.to_path_buf() });
    }
    let mut paths = Vec::new();
    for entry in fs::read_dir(dir).map_err(|e| ReportError::io(dir, e))? {
        let path = entry.map_err(|e| ReportError::io(dir, e))?.path();
        let ext = path.extension().and_then(|e| e.to_str());
        if matches!(ext, Some("pkl" | "safetensors")) && path.is_file() {
            paths.push(path);
        }
    }
    // Natural order so that warnings and duplicate resolution do not depend on read_dir order.
    paths.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));

    let mut files: BTreeMap<FileKey, PathBuf> = BTreeMap::new();
    for path in paths {
        let Some(key) = file_key(&path, warnings)? else { continue };
        match files.get(&key) {
            None => {
                files.insert(key, path);
            }
            // A converted pickle next to its original is the normal case: the native file
            // wins silently. Two files of the same kind holding the same set is a naming error.
            Some(kept) if is_native(kept) == is_native(&path) => warnings.push(format!(
                "{} and {} both hold {}-{}-{}; using the first",
                kept.display(),
                path.display(),
                key.0,
                key.1,
                key.2
            )),
            Some(_) => {
                if is_native(&path) {
                    files.insert(key, path);
                }
            }
        }
    }
    Ok(files)
}

fn is_native(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()) == Some(FILE_EXTENSION)
}

fn file_key(path: &Path, warnings: &mut Vec<String>) -> Result<Option<FileKey>, ReportError> {
    let from_name = native::FileMeta::from_file_name(path).unwrap_or_default();
    let meta = if is_native(path) {
        native::read_file_meta(path)
            .map_err(|source| ReportError::Data { path: path.to_path_buf(), source })?
    } else {
        native::FileMeta::default()
    };
    let env = meta.env.clone().or_else(|| from_name.env.clone());
    let index = meta.task_index.or(from_name.task_index);
    let mode = meta.mode.clone().or_else(|| from_name.mode.clone());
    let (Some(env), Some(index), Some(mode)) = (env, index, mode) else {
        warnings.push(format!(
            "{}: skipped, neither its name nor its metadata says env, task and mode \
             ({{env}}-{{task}}-{{mode}})",
            path.display()
        ));
        return Ok(None);
    };
    let differs =
        |a: &Option<String>, b: &Option<String>| matches!((a, b), (Some(x), Some(y)) if x != y);
    if differs(&meta.env, &from_name.env)
        || differs(&meta.mode, &from_name.mode)
        || matches!((meta.task_index, from_name.task_index), (Some(x), Some(y)) if x != y)
    {
        warnings.push(format!(
            "{}: its metadata says {env}-{index}-{mode}, its name says otherwise; using the \
             metadata",
            path.display()
        ));
    }
    Ok(Some((env, index, mode)))
}

/// The undiscounted return of every episode in a native file or a reference pickle, and, for a
/// family whose success shows in its rewards ([`pdt_envs::success_reward`]), the fraction of
/// episodes with a successful step.
pub(super) fn read_returns(path: &Path, env: &str) -> Result<(Vec<f64>, Option<f64>), ReportError> {
    let data = |source| ReportError::Data { path: path.to_path_buf(), source };
    let dataset: TaskDataset = if path.extension().and_then(|e| e.to_str()) == Some(FILE_EXTENSION)
    {
        native::read_task_dataset(path).map_err(data)?
    } else {
        load_pickle(path, &ReferenceOptions::default()).map_err(data)?.dataset
    };
    let success = pdt_envs::success_reward(env).map(|bar| {
        let wins = dataset.trajectories.iter().filter(|t| t.rewards.iter().any(|&r| r >= bar));
        wins.count() as f64 / dataset.trajectories.len().max(1) as f64
    });
    Ok((dataset.returns(), success))
}

/// Per task of `env`, the reference's expert return: its `expert` file if there is one, else its
/// `prompt-expert` file (the release ships only prompt sets for the Cheetah families).
pub(super) fn load_reference(
    files: &BTreeMap<FileKey, PathBuf>,
    env: &str,
) -> Result<BTreeMap<usize, ReferenceReturn>, ReportError> {
    let mut chosen: BTreeMap<usize, (&str, &PathBuf)> = BTreeMap::new();
    for ((e, index, mode), path) in files {
        if e != env {
            continue;
        }
        let better =
            matches!((mode.as_str(), chosen.get(index)), ("expert", _) | ("prompt-expert", None));
        if better {
            chosen.insert(*index, (mode.as_str(), path));
        }
    }
    let mut out = BTreeMap::new();
    for (index, (mode, path)) in chosen {
        if let Some(stat) = ReturnStat::of(&read_returns(path, env)?.0) {
            out.insert(index, ReferenceReturn { mode: mode.to_string(), path: path.clone(), stat });
        }
    }
    Ok(out)
}
