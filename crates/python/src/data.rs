//! Dataset files: reading native and reference files, writing native ones.

use crate::errors::NotFoundError;
use crate::{array2, existing, lib_error, value_error};
use numpy::prelude::*;
use numpy::{AllowTypeChange, PyArrayLike1, PyArrayLike2};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

/// Reads a dataset file: a native `.safetensors` file or a reference `.pkl` (read without
/// executing anything). Returns `{"obs_dim", "act_dim", "meta": {...} | None, "trajectories":
/// [{"observations": [T, obs_dim] float32, "actions": [T, act_dim] float32, "rewards": [T]
/// float32, "terminated": [T] bool, "truncated": [T] bool}, ...]}`.
#[pyfunction]
pub(crate) fn load_dataset<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    existing(&path, "dataset")?;
    let p = path.clone();
    let ds = py.detach(move || pdt_data::multitask::load_task_file(&p)).map_err(lib_error)?;
    let meta = match path.extension().and_then(|e| e.to_str()) {
        Some("safetensors") => Some(pdt_data::native::read_file_meta(&path).map_err(lib_error)?),
        _ => None,
    };
    let out = PyDict::new(py);
    out.set_item("obs_dim", ds.obs_dim)?;
    out.set_item("act_dim", ds.act_dim)?;
    match meta {
        Some(m) => {
            let d = PyDict::new(py);
            d.set_item("env", m.env)?;
            d.set_item("task", m.task_index)?;
            d.set_item("mode", m.mode)?;
            out.set_item("meta", d)?;
        }
        None => out.set_item("meta", py.None())?,
    }
    let mut trajs = Vec::with_capacity(ds.trajectories.len());
    for t in ds.trajectories {
        let n = t.rewards.len();
        let d = PyDict::new(py);
        d.set_item("observations", array2(py, t.observations, n, t.obs_dim)?)?;
        d.set_item("actions", array2(py, t.actions, n, t.act_dim)?)?;
        d.set_item("rewards", t.rewards.into_pyarray(py))?;
        d.set_item("terminated", t.terminated.into_pyarray(py))?;
        d.set_item("truncated", t.truncated.into_pyarray(py))?;
        trajs.push(d);
    }
    out.set_item("trajectories", trajs)?;
    Ok(out)
}

/// One trajectory's arrays from Python, checked against the dims.
fn trajectory_from_py(
    i: usize,
    t: &Bound<'_, PyDict>,
    obs_dim: usize,
    act_dim: usize,
) -> PyResult<pdt_data::Trajectory> {
    let get = |key: &str| -> PyResult<Bound<'_, PyAny>> {
        t.get_item(key)?.ok_or_else(|| value_error(format!("trajectory {i}: no `{key}`")))
    };
    let floats = |key: &str, cols: usize| -> PyResult<Vec<f32>> {
        let item = get(key)?;
        let a: PyArrayLike2<'_, f32, AllowTypeChange> = if cols == 0 {
            let v: PyArrayLike1<'_, f32, AllowTypeChange> = item.extract().map_err(|e| {
                value_error(format!("trajectory {i}: `{key}` is not a 1-D float array ({e})"))
            })?;
            return Ok(v.as_array().to_vec());
        } else {
            item.extract().map_err(|e| {
                value_error(format!("trajectory {i}: `{key}` is not a 2-D float array ({e})"))
            })?
        };
        if a.shape()[1] != cols {
            return Err(value_error(format!(
                "trajectory {i}: `{key}` has shape {:?}, expected [T, {cols}]",
                a.shape()
            )));
        }
        Ok(a.as_array().iter().copied().collect())
    };
    let flags = |key: &str| -> PyResult<Vec<bool>> {
        let v: PyArrayLike1<'_, bool, AllowTypeChange> = get(key)?.extract().map_err(|e| {
            value_error(format!("trajectory {i}: `{key}` is not a 1-D bool array ({e})"))
        })?;
        Ok(v.as_array().to_vec())
    };
    pdt_data::Trajectory::new(
        obs_dim,
        act_dim,
        floats("observations", obs_dim)?,
        floats("actions", act_dim)?,
        floats("rewards", 0)?,
        flags("terminated")?,
        flags("truncated")?,
    )
    .map_err(|e| value_error(format!("trajectory {i}: {e}")))
}

/// Writes trajectories (dicts with the keys `load_dataset` returns) as a native `.safetensors`
/// file, atomically (a temporary file, then a rename), after the reader's checks (finite values,
/// flags only at an episode's last step, shapes). With `env` (a family's name or a task suite
/// file's path), the family must exist and have `obs_dim` and `act_dim`
/// (`pdt_envs::check_dims`). The directory must exist.
#[pyfunction]
#[pyo3(signature = (path, trajectories, obs_dim, act_dim, env = None, task = None, mode = None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_dataset(
    py: Python<'_>,
    path: PathBuf,
    trajectories: Vec<Bound<'_, PyDict>>,
    obs_dim: usize,
    act_dim: usize,
    env: Option<String>,
    task: Option<usize>,
    mode: Option<String>,
) -> PyResult<()> {
    // A task suite's path (`suite.toml`) stands for the suite: its files record its name, the
    // name the loader finds them under (`{name}-{task}-{mode}`).
    let env = match env {
        Some(env) => {
            pdt_envs::check_dims(&env, obs_dim, act_dim).map_err(lib_error)?;
            Some(pdt_envs::family(&env).map_err(lib_error)?.name().to_owned())
        }
        None => None,
    };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        if !dir.is_dir() {
            return Err(NotFoundError::new_err(format!(
                "directory {} (to write {}): no such directory",
                dir.display(),
                path.display()
            )));
        }
    }
    let trajs = trajectories
        .iter()
        .enumerate()
        .map(|(i, t)| trajectory_from_py(i, t, obs_dim, act_dim))
        .collect::<PyResult<Vec<_>>>()?;
    let ds = pdt_data::TaskDataset { obs_dim, act_dim, trajectories: trajs };
    let meta = pdt_data::native::FileMeta { env, task_index: task, mode };
    py.detach(|| pdt_data::native::write_task_dataset(&path, &ds, &meta)).map_err(lib_error)
}

/// The episodes (indices into `returns`, one return per episode) that make a task's prompt set by
/// `rule` (`best:N`: the N highest returns, best first; `pdt_data::flat::PromptRule`), in order.
#[pyfunction]
pub(crate) fn prompt_indices(returns: Vec<f64>, rule: &str) -> PyResult<Vec<usize>> {
    let rule: pdt_data::flat::PromptRule =
        rule.parse().map_err(|e: String| value_error(format!("prompt_rule: {e}")))?;
    Ok(rule.pick(&returns))
}

/// Checks that data of `obs_dim` x `act_dim` can be the family `env`'s (`pdt_envs::check_dims`):
/// `ValueError` naming the family and both sizes, or the known families for an unknown one.
#[pyfunction]
pub(crate) fn check_dims(env: &str, obs_dim: usize, act_dim: usize) -> PyResult<()> {
    pdt_envs::check_dims(env, obs_dim, act_dim).map_err(lib_error)
}
