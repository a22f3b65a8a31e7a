//! The reference release's data files, `{env}-{task}-{mode}.pkl`, read into a [`TaskDataset`].
//!
//! Each file is a pickled `list` of trajectories; each trajectory a `dict` of numpy arrays:
//! `observations (T, obs_dim)`, `actions (T, act_dim)`, `rewards (T, 1)` or `(T,)`, `terminals`
//! (or `dones`) `(T, 1)` or `(T,)`, and optionally `next_observations`, which the reference never
//! reads and neither do we. float32 and float64 arrays are accepted (float64 is rounded to f32).
//! The file is read with [`crate::pickle`], which never executes code.
//!
//! The reference keeps a single `terminals` flag for two different things: a real end of the MDP
//! and the time limit. [`TerminalsAs`] says how to split it into `terminated` and `truncated`.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::pickle::{self, DType, NdArray, PyValue};
use crate::{DataError, TaskDataset, Trajectory};

/// How the reference's `terminals`/`dones` flags become `terminated` / `truncated`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TerminalsAs {
    /// A flag on the last step of a trajectory that is exactly `horizon` steps long is the time
    /// limit (truncated); any other flag is a real termination. The released prompt sets have
    /// horizon 200 and a flag only at step 199.
    Auto { horizon: usize },
    /// Every flag is a real termination.
    Terminated,
    /// Every flag is a time limit.
    Truncated,
}

impl Default for TerminalsAs {
    fn default() -> Self {
        TerminalsAs::Auto { horizon: 200 }
    }
}

/// Options for reading reference files.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReferenceOptions {
    pub terminals_as: TerminalsAs,
}

/// One array of a file, as stored: its key, numpy dtype name (`"float32"`) and the shape it has in
/// the first trajectory.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ArrayInfo {
    pub key: String,
    pub dtype: String,
    pub shape: Vec<usize>,
}

/// A reference file, read.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadedPickle {
    pub dataset: TaskDataset,
    /// Every array of the first trajectory, in the file's key order (including the ones that are
    /// not used, such as `next_observations`).
    pub arrays: Vec<ArrayInfo>,
}

/// Reads a reference `.pkl` file. Errors name the file, and for content errors the trajectory
/// index and the key.
pub fn load_pickle(path: &Path, opts: &ReferenceOptions) -> Result<LoadedPickle, DataError> {
    let bytes = pdt_base::fs::read_limited(path, pdt_base::fs::MAX_PICKLE_BYTES)
        .map_err(|source| DataError::Io { path: path.into(), source })?;
    let value = pickle::parse(&bytes).map_err(|e| DataError::from(e).in_file(path))?;
    convert(&value, opts).map_err(|message| DataError::Format { path: path.into(), message })
}

/// Reads a reference pickle from memory. Content errors name `<memory>` as the file.
pub fn from_bytes(bytes: &[u8], opts: &ReferenceOptions) -> Result<LoadedPickle, DataError> {
    let value = pickle::parse(bytes)?;
    convert(&value, opts)
        .map_err(|message| DataError::Format { path: PathBuf::from("<memory>"), message })
}

/// The file's value tree to a dataset; the error is a message without the file name.
fn convert(root: &PyValue, opts: &ReferenceOptions) -> Result<LoadedPickle, String> {
    let PyValue::List(items) = root else {
        return Err(format!("expected a list of trajectories, got {}", root.type_name()));
    };
    let Some(first) = items.first() else {
        return Err("the list of trajectories is empty".into());
    };
    let mut dims = None;
    let mut trajectories = Vec::with_capacity(items.len());
    for (i, item) in items.iter().enumerate() {
        let traj = trajectory(item, &mut dims, opts).map_err(|m| format!("trajectory {i}: {m}"))?;
        trajectories.push(traj);
    }
    let dataset = TaskDataset::new(trajectories).map_err(|e| e.to_string())?;
    Ok(LoadedPickle { dataset, arrays: array_infos(first) })
}

fn array_infos(traj: &PyValue) -> Vec<ArrayInfo> {
    let PyValue::Dict(pairs) = traj else { return Vec::new() };
    pairs
        .iter()
        .filter_map(|(k, v)| match (k, v) {
            (PyValue::Str(key), PyValue::NdArray(a)) => Some(ArrayInfo {
                key: key.clone(),
                dtype: a.dtype.name().to_string(),
                shape: a.shape.clone(),
            }),
            _ => None,
        })
        .collect()
}

/// numpy's way of writing a shape: `(5,)`, `(200, 20)`, `()`.
fn py_shape(shape: &[usize]) -> String {
    match shape {
        [d] => format!("({d},)"),
        _ => {
            let parts: Vec<String> = shape.iter().map(usize::to_string).collect();
            format!("({})", parts.join(", "))
        }
    }
}

fn array<'v>(traj: &'v PyValue, key: &str) -> Result<Option<&'v NdArray>, String> {
    match traj.get(key) {
        None => Ok(None),
        Some(PyValue::NdArray(a)) => Ok(Some(a)),
        Some(other) => Err(format!("`{key}` is a {}, expected a numpy array", other.type_name())),
    }
}

fn required<'v>(traj: &'v PyValue, key: &str) -> Result<&'v NdArray, String> {
    array(traj, key)?.ok_or_else(|| format!("no `{key}`"))
}

/// One trajectory. `dims` is `(obs_dim, act_dim)` of the first trajectory, which every other one
/// must match.
fn trajectory(
    traj: &PyValue,
    dims: &mut Option<(usize, usize)>,
    opts: &ReferenceOptions,
) -> Result<Trajectory, String> {
    if !matches!(traj, PyValue::Dict(_)) {
        return Err(format!("expected a dict of arrays, got {}", traj.type_name()));
    }
    let obs = required(traj, "observations")?;
    let act = required(traj, "actions")?;
    let rew = required(traj, "rewards")?;
    // The reference reads `terminals` when present, else `dones`.
    let (flags_key, flags) = match (array(traj, "terminals")?, array(traj, "dones")?) {
        (Some(a), _) => ("terminals", a),
        (None, Some(a)) => ("dones", a),
        (None, None) => return Err("no `terminals` or `dones`".into()),
    };

    let (t_len, obs_dim) = match obs.shape.as_slice() {
        [t, d] if *t >= 1 && *d >= 1 => (*t, *d),
        _ => {
            return Err(format!(
                "`observations` has shape {}, expected (T, obs_dim) with T >= 1",
                py_shape(&obs.shape)
            ))
        }
    };
    let act_dim = match act.shape.as_slice() {
        [t, d] if *t == t_len && *d >= 1 => *d,
        _ => {
            return Err(format!(
                "`actions` has shape {}, expected ({t_len}, act_dim)",
                py_shape(&act.shape)
            ))
        }
    };
    if let Some((obs0, act0)) = *dims {
        if obs_dim != obs0 {
            return Err(format!(
                "`observations` has shape {}, expected ({t_len}, {obs0}): obs_dim must be the \
                 same in every trajectory (trajectory 0 has {obs0})",
                py_shape(&obs.shape)
            ));
        }
        if act_dim != act0 {
            return Err(format!(
                "`actions` has shape {}, expected ({t_len}, {act0}): act_dim must be the same in \
                 every trajectory (trajectory 0 has {act0})",
                py_shape(&act.shape)
            ));
        }
    } else {
        *dims = Some((obs_dim, act_dim));
    }
    for (key, a) in [("rewards", rew), (flags_key, flags)] {
        if !matches!(a.shape.as_slice(), [t] | [t, 1] if *t == t_len) {
            return Err(format!(
                "`{key}` has shape {}, expected ({t_len},) or ({t_len}, 1)",
                py_shape(&a.shape)
            ));
        }
    }

    let observations = finite_f32("observations", obs, obs_dim)?;
    let actions = finite_f32("actions", act, act_dim)?;
    let rewards = finite_f32("rewards", rew, 1)?;
    let flags = flag_values(flags_key, flags)?;
    let (terminated, truncated) = split_flags(&flags, opts.terminals_as);
    Trajectory::new(obs_dim, act_dim, observations, actions, rewards, terminated, truncated)
        .map_err(|e| e.to_string())
}

/// The array as f32 (C order), refusing NaN and infinities, including float64 values that
/// overflow f32. `row` is the number of values per step, for the error message.
fn finite_f32(key: &str, a: &NdArray, row: usize) -> Result<Vec<f32>, String> {
    let values = a.to_f32_vec().ok_or_else(|| {
        format!("`{key}` has dtype {}, expected float32 or float64", a.dtype.name())
    })?;
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        let step = i / row.max(1);
        let original = a.to_f64_vec().get(i).copied().unwrap_or(f64::NAN);
        let detail = if a.dtype == DType::Float64 && original.is_finite() {
            format!("{original:e} does not fit float32")
        } else {
            format!("{original}")
        };
        return Err(format!("`{key}` has a value that is not finite at step {step}: {detail}"));
    }
    Ok(values)
}

/// Terminal flags as booleans. bool arrays are the norm; numeric 0/1 arrays are accepted too,
/// anything else is refused rather than guessed at.
fn flag_values(key: &str, a: &NdArray) -> Result<Vec<bool>, String> {
    if a.dtype == DType::Bool {
        return Ok(a.data.iter().map(|&b| b != 0).collect());
    }
    a.to_f64_vec()
        .into_iter()
        .enumerate()
        .map(|(t, v)| {
            if v == 0.0 {
                Ok(false)
            } else if v == 1.0 {
                Ok(true)
            } else {
                Err(format!("`{key}` has value {v} at step {t}, expected 0 or 1"))
            }
        })
        .collect()
}

/// Splits the reference's flags into (terminated, truncated).
fn split_flags(flags: &[bool], how: TerminalsAs) -> (Vec<bool>, Vec<bool>) {
    let t_len = flags.len();
    let mut terminated = vec![false; t_len];
    let mut truncated = vec![false; t_len];
    for (t, _) in flags.iter().enumerate().filter(|(_, &f)| f) {
        let is_time_limit = match how {
            TerminalsAs::Terminated => false,
            TerminalsAs::Truncated => true,
            TerminalsAs::Auto { horizon } => t + 1 == t_len && t_len == horizon,
        };
        let slot = if is_time_limit { truncated.get_mut(t) } else { terminated.get_mut(t) };
        if let Some(slot) = slot {
            *slot = true;
        }
    }
    // A trajectory whose last step carries no flag was cut off by whoever wrote the file (a
    // replay-buffer slice, a collection run that stopped): nothing says the MDP ended there, so
    // it is a truncation. Marking it keeps the invariant that every trajectory ends in exactly
    // the flag that describes its end, and never lets it pass for a real termination (which
    // would tell a value estimate that no reward follows).
    let last_flagged = flags.last().copied().unwrap_or(true);
    if !last_flagged {
        if let Some(last) = truncated.last_mut() {
            *last = true;
        }
    }
    (terminated, truncated)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_splits_time_limit_from_termination() {
        let how = TerminalsAs::Auto { horizon: 3 };
        // Full-length, flagged at the end: time limit.
        assert_eq!(
            split_flags(&[false, false, true], how),
            (vec![false; 3], vec![false, false, true])
        );
        // Shorter than the horizon, flagged at the end: termination.
        assert_eq!(split_flags(&[false, true], how), (vec![false, true], vec![false, false]));
        // A flag before the end is a termination even at full length.
        assert_eq!(
            split_flags(&[true, false, true], how),
            (vec![true, false, false], vec![false, false, true])
        );
        // No flag at the end: cut off, so truncated there.
        assert_eq!(
            split_flags(&[false, false, false, false], how),
            (vec![false; 4], vec![false, false, false, true])
        );
    }

    #[test]
    fn explicit_modes_ignore_length() {
        assert_eq!(
            split_flags(&[false, true], TerminalsAs::Terminated),
            (vec![false, true], vec![false, false])
        );
        assert_eq!(
            split_flags(&[false, true], TerminalsAs::Truncated),
            (vec![false, false], vec![false, true])
        );
    }

    #[test]
    fn shapes_print_like_numpy() {
        assert_eq!(py_shape(&[5]), "(5,)");
        assert_eq!(py_shape(&[200, 20]), "(200, 20)");
        assert_eq!(py_shape(&[]), "()");
    }
}
