//! The environment families and their vector of environments stepped on worker threads.

use crate::{array2, lib_error, lock, uint_list, usize_arg, usize_list, value_error};
use numpy::prelude::*;
use numpy::{AllowTypeChange, PyArray1, PyArray2, PyArrayLikeDyn};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::sync::Mutex;

/// The environment families: `{name: {"num_tasks", "obs_dim", "act_dim", "horizon", "rtg_scale",
/// "target_return", "prompt_length", "splits": {split: (train tasks, test tasks)}, "action_low",
/// "action_high" (per dimension), "success_reward" (or None), "scripted" (datasets from
/// scripted policies, else from an RL agent), "render_fps"}}`: all of it from pdt-envs, so a new family needs no
/// edit in the Python package.
#[pyfunction]
pub(crate) fn families(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let out = PyDict::new(py);
    for name in pdt_envs::FAMILY_NAMES {
        out.set_item(name, family_dict(py, name)?)?;
    }
    Ok(out)
}

/// One family's sizes, splits, bounds and tasks, as [`families`] gives each: a built-in family's
/// name or a task suite file's path (its `name` is the suite's own, the name its files carry).
#[pyfunction]
pub(crate) fn family_info<'py>(py: Python<'py>, env: &str) -> PyResult<Bound<'py, PyDict>> {
    family_dict(py, env)
}

fn family_dict<'py>(py: Python<'py>, env: &str) -> PyResult<Bound<'py, PyDict>> {
    let f = pdt_envs::family(env).map_err(lib_error)?;
    let p = f.preset();
    let d = PyDict::new(py);
    d.set_item("name", f.name())?;
    d.set_item("num_tasks", f.num_tasks())?;
    d.set_item("obs_dim", p.obs_dim)?;
    d.set_item("act_dim", p.act_dim)?;
    d.set_item("horizon", p.horizon)?;
    d.set_item("rtg_scale", p.rtg_scale)?;
    d.set_item("target_return", p.target_return)?;
    d.set_item("prompt_length", p.prompt_length)?;
    let splits = PyDict::new(py);
    for s in f.split_names() {
        splits.set_item(&s, f.split(&s).map_err(lib_error)?)?;
    }
    d.set_item("splits", splits)?;
    let bounds = f.action_bounds();
    d.set_item("action_low", bounds.low)?;
    d.set_item("action_high", bounds.high)?;
    d.set_item("success_reward", f.success_reward())?;
    d.set_item("scripted", f.scripted().is_some())?;
    d.set_item("render_fps", f.render_fps())?;
    // A suite's tasks have names (its splits and users' data name them); the built-in families'
    // are their indices.
    let names: Vec<String> = if pdt_envs::suite::is_suite_path(env) {
        let suite =
            pdt_envs::suite::SuiteFamily::load(std::path::Path::new(env)).map_err(lib_error)?;
        suite.tasks().iter().map(|t| t.name.clone()).collect()
    } else {
        (0..f.num_tasks()).map(|t| t.to_string()).collect()
    };
    d.set_item("task_names", names)?;
    Ok(d)
}

/// A task's parameters as JSON text (`{"goal": [x, y]}`, `{"velocity": v}`, ...).
#[pyfunction]
pub(crate) fn task_params(family: &str, task: &Bound<'_, PyAny>) -> PyResult<String> {
    let f = pdt_envs::family(family).map_err(lib_error)?;
    let task =
        usize_arg("task", task, &format!("a task index of {} (0..{})", f.name(), f.num_tasks()))?;
    Ok(f.task_params(task).map_err(lib_error)?.to_string())
}

struct VecState {
    venv: pdt_envs::vec_env::VecEnv,
    obs_dim: usize,
    /// The last step's success flags (Meta-World reach); `None` for families without them.
    success: Option<Vec<bool>>,
}

/// Environments of one family (each of its own task) stepped together on worker threads.
/// `promptdt.envs.make_vec` wraps it as a gymnasium `VectorEnv`.
#[pyclass(module = "promptdt._native", frozen)]
pub(crate) struct VecEnv {
    state: Mutex<VecState>,
    #[pyo3(get)]
    family: String,
    #[pyo3(get)]
    tasks: Vec<usize>,
    #[pyo3(get)]
    obs_dim: usize,
    #[pyo3(get)]
    act_dim: usize,
    #[pyo3(get)]
    horizon: usize,
}

#[pymethods]
impl VecEnv {
    /// One environment per entry of `tasks` (task indices of `family`, repeats allowed), stepped
    /// on `threads` threads (0 or None: one per core, at most one per environment).
    #[new]
    #[pyo3(signature = (family, tasks, threads = None))]
    fn new(
        family: &str,
        tasks: &Bound<'_, PyAny>,
        threads: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let f = pdt_envs::family(family).map_err(lib_error)?;
        let expected = format!("task indices of {} (0..{})", f.name(), f.num_tasks());
        let tasks = usize_list("tasks", tasks, &expected)?;
        let threads = match threads {
            Some(t) => usize_arg("threads", t, "a number of threads (0: one per core)")?,
            None => 0,
        };
        if tasks.is_empty() {
            return Err(value_error("tasks: an empty list given, expected at least one task"));
        }
        let envs =
            tasks.iter().map(|&t| f.make(t)).collect::<Result<Vec<_>, _>>().map_err(lib_error)?;
        let (obs_dim, act_dim, horizon) = (envs[0].obs_dim(), envs[0].act_dim(), envs[0].horizon());
        let threads = pdt_base::threads(threads);
        let venv = pdt_envs::vec_env::VecEnv::new(envs, threads);
        Ok(Self {
            state: Mutex::new(VecState { venv, obs_dim, success: None }),
            family: f.name().to_string(),
            tasks,
            obs_dim,
            act_dim,
            horizon,
        })
    }

    #[getter]
    fn num_envs(&self) -> usize {
        self.tasks.len()
    }

    /// Resets environment `indices[i]` with `seeds[i]` (all of them, in order, when `indices` is
    /// None); returns their first observations, `[len(seeds), obs_dim]` float32.
    #[pyo3(signature = (seeds, indices = None))]
    fn reset<'py>(
        &self,
        py: Python<'py>,
        seeds: &Bound<'py, PyAny>,
        indices: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let n = self.tasks.len();
        let seeds = uint_list("seeds", seeds, "a seed in [0, 2**64)")?;
        let indices = match indices {
            Some(v) => usize_list("indices", v, &format!("an environment index (0..{n})"))?,
            None => (0..n).collect(),
        };
        if indices.len() != seeds.len() {
            return Err(value_error(format!(
                "reset: {} seeds for {} environments",
                seeds.len(),
                indices.len()
            )));
        }
        if let Some(i) = indices.iter().find(|&&i| i >= n) {
            return Err(value_error(format!("reset: environment {i} of {n}")));
        }
        let resets: Vec<(usize, u64)> = indices.into_iter().zip(seeds).collect();
        let (obs, ds) = py.detach(|| -> PyResult<(Vec<f32>, usize)> {
            let mut st = lock(&self.state)?;
            let first = st.venv.reset_some(&resets).map_err(lib_error)?;
            Ok((first.concat(), st.obs_dim))
        })?;
        array2(py, obs, resets.len(), ds)
    }

    /// Steps environment i with `actions[i]` where `mask[i]` (every one without a mask). Returns
    /// `(observations [n, obs_dim] float32, rewards [n] float32, terminated [n] bool, truncated
    /// [n] bool)`; rows of environments not stepped are zeros and false.
    #[pyo3(signature = (actions, mask = None))]
    #[allow(clippy::type_complexity)]
    fn step<'py>(
        &self,
        py: Python<'py>,
        actions: PyArrayLikeDyn<'py, f32, AllowTypeChange>,
        mask: Option<Vec<bool>>,
    ) -> PyResult<(
        Bound<'py, PyArray2<f32>>,
        Bound<'py, PyArray1<f32>>,
        Bound<'py, PyArray1<bool>>,
        Bound<'py, PyArray1<bool>>,
    )> {
        let n = self.tasks.len();
        let shape = actions.shape().to_vec();
        if shape != [n, self.act_dim] {
            return Err(value_error(format!(
                "actions: shape {shape:?}, expected [{n}, {}] (num_envs, act_dim)",
                self.act_dim
            )));
        }
        let flat: Vec<f32> = actions.as_array().iter().copied().collect();
        // Checked here, before any environment steps: an environment refusing its action would
        // otherwise raise after the others had stepped, and their results would be lost.
        if let Some(k) = flat.iter().position(|x| !x.is_finite()) {
            let (i, j) = (k / self.act_dim, k % self.act_dim);
            return Err(value_error(format!(
                "actions[{i}, {j}] = {} is not a finite number (environment {i}, task {})",
                flat[k], self.tasks[i]
            )));
        }
        if let Some(m) = &mask {
            if m.len() != n {
                return Err(value_error(format!("mask: {} entries for {n} environments", m.len())));
            }
        }
        let (obs, rew, term, trunc) = py.detach(|| -> PyResult<_> {
            let mut st = lock(&self.state)?;
            let ds = st.obs_dim;
            let slots = st.venv.step_flat(&flat, mask.as_deref()).map_err(lib_error)?;
            let (mut obs, mut rew) = (vec![0f32; n * ds], vec![0f32; n]);
            let (mut term, mut trunc) = (vec![false; n], vec![false; n]);
            let mut success: Option<Vec<bool>> = None;
            for (i, slot) in slots.into_iter().enumerate() {
                if let Some(r) = slot {
                    let s = r.map_err(|e| value_error(format!("environment {i}: {e}")))?;
                    obs[i * ds..(i + 1) * ds].copy_from_slice(&s.obs);
                    rew[i] = s.reward;
                    term[i] = s.terminated;
                    trunc[i] = s.truncated;
                    if let Some(ok) = s.success {
                        success.get_or_insert_with(|| vec![false; n])[i] = ok;
                    }
                }
            }
            st.success = success;
            Ok((obs, rew, term, trunc))
        })?;
        Ok((
            array2(py, obs, n, self.obs_dim)?,
            rew.into_pyarray(py),
            term.into_pyarray(py),
            trunc.into_pyarray(py),
        ))
    }

    /// The last `step`'s success flags `[n] bool` (Meta-World reach: the hand within 0.05 of the
    /// goal; false for environments not stepped), or `None` for families without a success
    /// criterion or before the first step.
    fn last_success<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray1<bool>>>> {
        let st = lock(&self.state)?;
        Ok(st.success.clone().map(|v| v.into_pyarray(py)))
    }
}

impl VecEnv {
    /// Runs `f` on the Rust vector env, under its lock (`src/render.rs` renders through it).
    pub(crate) fn with_venv<R>(
        &self,
        f: impl FnOnce(&mut pdt_envs::vec_env::VecEnv) -> R,
    ) -> PyResult<R> {
        Ok(f(&mut lock(&self.state)?.venv))
    }
}
