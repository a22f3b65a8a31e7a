//! Every field of a suite file checked, each error naming the file, the field and why.

use super::file::{RawSplit, RawSuite, RawTask};
use super::{SuiteError, SuiteFamily, SuiteSplit, SuiteTask};
use crate::worker::WorkerSpec;
use crate::{ActionBounds, EnvPreset, FAMILY_NAMES};
use serde::Deserialize;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Sizes above this are typing mistakes, not suites (and would ask for absurd allocations).
const MAX_SIZE: i64 = 1 << 24;

/// The error of `field` in the file at `path`.
fn bad(path: &Path, field: impl Into<String>, why: impl Into<String>) -> SuiteError {
    SuiteError::Field { path: path.to_path_buf(), field: field.into(), why: why.into() }
}

/// A size field: a whole number in `1..=MAX_SIZE`.
fn size(path: &Path, field: &str, v: i64) -> Result<usize, SuiteError> {
    if !(1..=MAX_SIZE).contains(&v) {
        return Err(bad(path, field, format!("is {v}; it must be between 1 and {MAX_SIZE}")));
    }
    Ok(v as usize)
}

/// A number that must be finite (TOML allows `nan` and `inf`), as f32 without overflow.
fn finite(path: &Path, field: &str, v: f64) -> Result<f32, SuiteError> {
    if !v.is_finite() || !(v as f32).is_finite() {
        return Err(bad(path, field, format!("is {v}; it must be a finite number")));
    }
    Ok(v as f32)
}

/// Reads the checked suite out of `raw`, the file at `path` (`dir`: its directory, against which
/// relative paths resolve) whose text is `text`.
pub(super) fn check(path: &Path, text: String, raw: RawSuite) -> Result<SuiteFamily, SuiteError> {
    let name = check_name(path, &raw.name)?;
    let obs_dim = size(path, "obs_dim", raw.obs_dim)?;
    let act_dim = size(path, "act_dim", raw.act_dim)?;
    let horizon = size(path, "max_ep_len", raw.max_ep_len)?;
    let prompt_length = size(path, "prompt_length", raw.prompt_length)?;
    if prompt_length > horizon {
        return Err(bad(
            path,
            "prompt_length",
            format!("is {prompt_length}, longer than an episode (max_ep_len = {horizon})"),
        ));
    }
    let rtg_scale = finite(path, "rtg_scale", raw.rtg_scale)?;
    if rtg_scale <= 0.0 {
        return Err(bad(path, "rtg_scale", format!("is {rtg_scale}; it must be above 0")));
    }
    let bounds = check_bounds(path, &raw, act_dim)?;
    let render_fps = match raw.render_fps {
        None => None,
        Some(v) if (1..=10_000).contains(&v) => Some(v as u32),
        Some(v) => return Err(bad(path, "render_fps", format!("is {v}; it must be in 1..=10000"))),
    };
    let success_reward =
        raw.success_reward.map(|v| finite(path, "success_reward", v)).transpose()?;
    let tasks = raw
        .tasks
        .into_iter()
        .enumerate()
        .map(|(i, v)| check_task(path, i, v))
        .collect::<Result<Vec<_>, _>>()?;
    let index = task_index(path, &tasks)?;
    let target_return = check_target(path, raw.target_return, &tasks)?;
    if raw.splits.0.is_empty() {
        return Err(bad(path, "splits", "declares no split (give at least [splits.default])"));
    }
    let splits = raw
        .splits
        .0
        .into_iter()
        .map(|(name, v)| check_split(path, name, v, &index))
        .collect::<Result<Vec<_>, _>>()?;
    let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let environment = raw.environment.map(|v| check_environment(path, &dir, v)).transpose()?;
    let preset = EnvPreset { obs_dim, act_dim, horizon, rtg_scale, target_return, prompt_length };
    Ok(SuiteFamily {
        path: path.to_path_buf(),
        text,
        name,
        preset,
        bounds,
        render_fps,
        success_reward,
        tasks,
        splits,
        environment,
    })
}

/// The suite's name names its data files (`{name}-{task}-{mode}`): a file-name-safe word that is
/// not a built-in family's (data of the two would be mistaken for each other).
fn check_name(path: &Path, name: &str) -> Result<String, SuiteError> {
    let ok = |c: char| c.is_ascii_alphanumeric() || c == '_' || c == '-';
    if name.is_empty() || !name.chars().all(ok) {
        return Err(bad(
            path,
            "name",
            format!("is {name:?}; it names the data files, so it must be letters, digits, _ or -"),
        ));
    }
    if FAMILY_NAMES.iter().any(|f| f.replace('_', "-") == name.replace('_', "-")) {
        return Err(bad(
            path,
            "name",
            format!("is {name:?}, a built-in family's name; a suite needs a name of its own"),
        ));
    }
    Ok(name.to_owned())
}

/// Either `action_bound` (symmetric) or both `action_low` and `action_high`, never both ways.
fn check_bounds(path: &Path, raw: &RawSuite, act_dim: usize) -> Result<ActionBounds, SuiteError> {
    match (raw.action_bound, &raw.action_low, &raw.action_high) {
        (Some(b), None, None) => {
            let b = finite(path, "action_bound", b)?;
            if b <= 0.0 {
                return Err(bad(path, "action_bound", format!("is {b}; it must be above 0")));
            }
            Ok(ActionBounds::symmetric(b, act_dim))
        }
        (None, Some(low), Some(high)) => {
            let side = |field: &str, v: &[f64]| -> Result<Vec<f32>, SuiteError> {
                if v.len() != act_dim {
                    return Err(bad(
                        path,
                        field,
                        format!("has {} values; act_dim is {act_dim}", v.len()),
                    ));
                }
                v.iter()
                    .enumerate()
                    .map(|(i, x)| finite(path, &format!("{field}[{i}]"), *x))
                    .collect()
            };
            let (low, high) = (side("action_low", low)?, side("action_high", high)?);
            if let Some(i) = (0..act_dim).find(|&i| low[i] >= high[i]) {
                return Err(bad(
                    path,
                    format!("action_low[{i}]"),
                    format!("is {}, not below action_high[{i}] = {}", low[i], high[i]),
                ));
            }
            Ok(ActionBounds { low, high })
        }
        (Some(_), _, _) => Err(bad(
            path,
            "action_bound",
            "is given together with action_low/action_high; give one or the other",
        )),
        (None, None, None) => Err(bad(
            path,
            "action_bound",
            "is missing: give action_bound (one symmetric bound) or action_low and action_high",
        )),
        (None, Some(_), None) => Err(bad(path, "action_high", "is missing (action_low is given)")),
        (None, None, Some(_)) => Err(bad(path, "action_low", "is missing (action_high is given)")),
    }
}

fn check_task(path: &Path, i: usize, v: toml::Value) -> Result<SuiteTask, SuiteError> {
    let field = format!("tasks[{i}]");
    let raw = RawTask::deserialize(v).map_err(|e| bad(path, &field, e.message()))?;
    if raw.name.is_empty() {
        return Err(bad(path, format!("{field}.name"), "is empty"));
    }
    let params = match raw.params {
        None => serde_json::Value::Object(Default::default()),
        Some(p @ toml::Value::Table(_)) => {
            check_finite_params(path, &format!("{field}.params"), &p)?;
            serde_json::to_value(p)
                .map_err(|e| bad(path, format!("{field}.params"), e.to_string()))?
        }
        Some(other) => {
            return Err(bad(
                path,
                format!("{field}.params"),
                format!(
                    "is a {}; it must be a table, e.g. params = {{ mass = 1.0 }}",
                    other.type_str()
                ),
            ))
        }
    };
    let num = |key: &str, v: Option<f64>| {
        v.map(|x| finite(path, &format!("{field}.{key}"), x)).transpose()
    };
    let target_return = num("target_return", raw.target_return)?;
    let expert = num("expert_return", raw.expert_return)?;
    let random = num("random_return", raw.random_return)?;
    let reference = match (expert, random) {
        (Some(e), Some(r)) if e > r => Some((f64::from(e), f64::from(r))),
        (Some(e), Some(r)) => {
            return Err(bad(
                path,
                format!("{field}.expert_return"),
                format!(
                "is {e}, not above random_return = {r}: a normalised score needs expert > random"
            ),
            ))
        }
        (Some(_), None) => {
            return Err(bad(
                path,
                format!("{field}.random_return"),
                "is missing (expert_return is given)",
            ))
        }
        (None, Some(_)) => {
            return Err(bad(
                path,
                format!("{field}.expert_return"),
                "is missing (random_return is given)",
            ))
        }
        (None, None) => None,
    };
    Ok(SuiteTask { name: raw.name, params, target_return, reference })
}

/// NaN or infinite numbers anywhere in a task's parameters (TOML allows them; the JSON of dataset
/// cards and of the worker's messages does not).
fn check_finite_params(path: &Path, field: &str, v: &toml::Value) -> Result<(), SuiteError> {
    match v {
        toml::Value::Float(x) if !x.is_finite() => {
            Err(bad(path, field, format!("is {x}; parameters must be finite numbers")))
        }
        toml::Value::Table(t) => {
            t.iter().try_for_each(|(k, x)| check_finite_params(path, &format!("{field}.{k}"), x))
        }
        toml::Value::Array(a) => a
            .iter()
            .enumerate()
            .try_for_each(|(i, x)| check_finite_params(path, &format!("{field}[{i}]"), x)),
        _ => Ok(()),
    }
}

/// Task name -> index; at least one task, no name twice.
fn task_index(path: &Path, tasks: &[SuiteTask]) -> Result<HashMap<String, usize>, SuiteError> {
    if tasks.is_empty() {
        return Err(bad(path, "tasks", "is empty: declare at least one [[tasks]]"));
    }
    let mut index = HashMap::new();
    for (i, t) in tasks.iter().enumerate() {
        if let Some(first) = index.insert(t.name.clone(), i) {
            return Err(bad(
                path,
                format!("tasks[{i}].name"),
                format!("is {:?}, already the name of tasks[{first}]", t.name),
            ));
        }
    }
    Ok(index)
}

/// The suite's target return: the top-level one, else (every task having its own) the largest of
/// the tasks' (what the return-token checks must admit).
fn check_target(path: &Path, top: Option<f64>, tasks: &[SuiteTask]) -> Result<f32, SuiteError> {
    if let Some(t) = top {
        return finite(path, "target_return", t);
    }
    match tasks.iter().position(|t| t.target_return.is_none()) {
        Some(i) => Err(bad(
            path,
            "target_return",
            format!(
                "is missing: give one for the suite, or one in every [[tasks]] (tasks[{i}] has none)"
            ),
        )),
        None => Ok(tasks.iter().filter_map(|t| t.target_return).fold(f32::MIN, f32::max)),
    }
}

fn check_split(
    path: &Path,
    name: String,
    v: toml::Value,
    index: &HashMap<String, usize>,
) -> Result<SuiteSplit, SuiteError> {
    let field = format!("splits.{name}");
    let raw = RawSplit::deserialize(v).map_err(|e| bad(path, &field, e.message()))?;
    let resolve = |side: &str, names: &[String]| -> Result<Vec<usize>, SuiteError> {
        if names.is_empty() {
            return Err(bad(path, format!("{field}.{side}"), "is empty"));
        }
        let mut out: Vec<usize> = Vec::with_capacity(names.len());
        for (j, n) in names.iter().enumerate() {
            let place = format!("{field}.{side}[{j}]");
            let Some(&t) = index.get(n) else {
                let mut known: Vec<&str> = index.keys().map(String::as_str).collect();
                known.sort_unstable();
                return Err(bad(
                    path,
                    place,
                    format!("names no task: {n:?} (tasks: {})", known.join(", ")),
                ));
            };
            if out.contains(&t) {
                return Err(bad(path, place, format!("names {n:?} a second time")));
            }
            out.push(t);
        }
        Ok(out)
    };
    let train = resolve("train", &raw.train)?;
    let test = resolve("test", &raw.test)?;
    if let Some(j) = test.iter().position(|t| train.contains(t)) {
        return Err(bad(
            path,
            format!("{field}.test[{j}]"),
            format!(
                "{:?} is also in {field}.train: a held-out task must not be trained on",
                raw.test[j]
            ),
        ));
    }
    Ok(SuiteSplit { name, train, test })
}

fn check_environment(path: &Path, dir: &Path, v: toml::Value) -> Result<WorkerSpec, SuiteError> {
    let mut spec = WorkerSpec::deserialize(v).map_err(|e| bad(path, "environment", e.message()))?;
    if spec.entry.trim().is_empty() {
        return Err(bad(
            path,
            "environment.entry",
            "is empty: give a gymnasium id or module:callable",
        ));
    }
    if !(spec.step_timeout_s.is_finite() && spec.step_timeout_s > 0.0) {
        return Err(bad(
            path,
            "environment.step_timeout_s",
            format!("is {}; it must be a finite number of seconds above 0", spec.step_timeout_s),
        ));
    }
    if spec.task_keyword.as_deref().is_some_and(str::is_empty) {
        return Err(bad(path, "environment.task_keyword", "is empty (leave it out instead)"));
    }
    spec.python = spec.python.map(|p| resolve_program(dir, p));
    Ok(spec)
}

/// A relative interpreter path (`.venv/bin/python`) is taken from the suite file's directory; a
/// bare command name (`python3`) stays a name looked up on `PATH`.
fn resolve_program(dir: &Path, p: PathBuf) -> PathBuf {
    if p.is_relative() && p.components().count() > 1 {
        dir.join(p)
    } else {
        p
    }
}
