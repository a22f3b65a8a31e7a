//! `promptdt._native`: the Rust side of the Python package (PyO3).
//!
//! Thin bindings over the library crates, the same calls the CLI makes: a trained run's policy
//! (`pdt_policy::Policy`, each episode a `pdt_policy::Episode`, the runtime `promptdt serve` acts
//! through too, so that Python rollouts take
//! `promptdt eval`'s actions), the environment families behind a vector of environments stepped on
//! worker threads (`pdt_envs::vec_env::VecEnv`), the dataset readers (native files and the
//! reference pickles, through the safe reader), and training, evaluation and collection. The
//! Python layer (`python/promptdt`) adds the gymnasium vector env, dataclasses and Minari.
//!
//! Arrays cross as numpy arrays: outputs are moved into numpy without a copy (a Rust `Vec` becomes
//! the array's buffer), inputs are read in place when they already have the dtype and layout
//! wanted, converted otherwise. Every error is a Python exception naming the file, field or shape.
//! Long calls release the GIL.

use numpy::prelude::*;
use numpy::{AllowTypeChange, PyArray1, PyArray2, PyArrayLike1, PyArrayLike2};
use pdt_model::PrefixCache;
use pdt_policy::{Episode, Inputs, PolicyError, PromptArrays, Target};
use pdt_prompt::SegmentBatch;
use pyo3::exceptions::{PyFileNotFoundError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};
use tch::Tensor;

fn value_error(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

fn lock<T>(m: &Mutex<T>) -> PyResult<MutexGuard<'_, T>> {
    // A panic while the lock was held (none is expected) leaves the state unusable, not unsafe.
    m.lock().map_err(|_| PyRuntimeError::new_err("internal state poisoned by an earlier panic"))
}

fn existing(path: &Path, what: &str) -> PyResult<()> {
    if path.exists() {
        Ok(())
    } else {
        Err(PyFileNotFoundError::new_err(format!(
            "{what} {}: no such file or directory",
            path.display()
        )))
    }
}

/// A `[rows, cols]` numpy array that owns `v` (no copy).
fn array2<'py, T: numpy::Element>(
    py: Python<'py>,
    v: Vec<T>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'py, PyArray2<T>>> {
    v.into_pyarray(py).reshape([rows, cols]).map_err(value_error)
}

// ------------------------------------------------------------------------------------------------
// Datasets
// ------------------------------------------------------------------------------------------------

/// Reads a dataset file: a native `.safetensors` file or a reference `.pkl` (read without
/// executing anything). Returns `{"obs_dim", "act_dim", "meta": {...} | None, "trajectories":
/// [{"observations": [T, obs_dim] float32, "actions": [T, act_dim] float32, "rewards": [T]
/// float32, "terminated": [T] bool, "truncated": [T] bool}, ...]}`.
#[pyfunction]
fn load_dataset<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    existing(&path, "dataset")?;
    let p = path.clone();
    let ds = py.detach(move || pdt_data::multitask::load_task_file(&p)).map_err(value_error)?;
    let meta = match path.extension().and_then(|e| e.to_str()) {
        Some("safetensors") => Some(pdt_data::native::read_file_meta(&path).map_err(value_error)?),
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
/// flags only at an episode's last step, shapes).
#[pyfunction]
#[pyo3(signature = (path, trajectories, obs_dim, act_dim, env = None, task = None, mode = None))]
#[allow(clippy::too_many_arguments)]
fn write_dataset(
    py: Python<'_>,
    path: PathBuf,
    trajectories: Vec<Bound<'_, PyDict>>,
    obs_dim: usize,
    act_dim: usize,
    env: Option<String>,
    task: Option<usize>,
    mode: Option<String>,
) -> PyResult<()> {
    let trajs = trajectories
        .iter()
        .enumerate()
        .map(|(i, t)| trajectory_from_py(i, t, obs_dim, act_dim))
        .collect::<PyResult<Vec<_>>>()?;
    let ds = pdt_data::TaskDataset { obs_dim, act_dim, trajectories: trajs };
    let meta = pdt_data::native::FileMeta { env, task_index: task, mode };
    py.detach(|| pdt_data::native::write_task_dataset(&path, &ds, &meta)).map_err(value_error)
}

// ------------------------------------------------------------------------------------------------
// Environments
// ------------------------------------------------------------------------------------------------

/// The environment families: `{name: {"num_tasks", "obs_dim", "act_dim", "horizon", "rtg_scale",
/// "target_return", "prompt_length", "splits": {split: (train tasks, test tasks)}, "action_low",
/// "action_high" (per dimension), "success_reward" (or None), "scripted" (datasets from
/// scripted policies, else from an RL agent)}}`: all of it from pdt-envs, so a new family needs no
/// edit in the Python package.
#[pyfunction]
fn families(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let out = PyDict::new(py);
    for name in pdt_envs::FAMILY_NAMES {
        let f = pdt_envs::family(name).map_err(value_error)?;
        let p = f.preset();
        let d = PyDict::new(py);
        d.set_item("num_tasks", f.num_tasks())?;
        d.set_item("obs_dim", p.obs_dim)?;
        d.set_item("act_dim", p.act_dim)?;
        d.set_item("horizon", p.horizon)?;
        d.set_item("rtg_scale", p.rtg_scale)?;
        d.set_item("target_return", p.target_return)?;
        d.set_item("prompt_length", p.prompt_length)?;
        let splits = PyDict::new(py);
        for s in f.split_names() {
            splits.set_item(&s, f.split(&s).map_err(value_error)?)?;
        }
        d.set_item("splits", splits)?;
        let bounds = f.action_bounds();
        d.set_item("action_low", bounds.low)?;
        d.set_item("action_high", bounds.high)?;
        d.set_item("success_reward", f.success_reward())?;
        d.set_item("scripted", f.scripted().is_some())?;
        out.set_item(name, d)?;
    }
    Ok(out)
}

/// A task's parameters as JSON text (`{"goal": [x, y]}`, `{"velocity": v}`, ...).
#[pyfunction]
fn task_params(family: &str, task: usize) -> PyResult<String> {
    let f = pdt_envs::family(family).map_err(value_error)?;
    Ok(f.task_params(task).map_err(value_error)?.to_string())
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
struct VecEnv {
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
    /// on `threads` threads (0: one per core, at most one per environment).
    #[new]
    #[pyo3(signature = (family, tasks, threads = 0))]
    fn new(family: &str, tasks: Vec<usize>, threads: usize) -> PyResult<Self> {
        let f = pdt_envs::family(family).map_err(value_error)?;
        if tasks.is_empty() {
            return Err(value_error("tasks: give at least one task"));
        }
        let envs =
            tasks.iter().map(|&t| f.make(t)).collect::<Result<Vec<_>, _>>().map_err(value_error)?;
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
        seeds: Vec<u64>,
        indices: Option<Vec<usize>>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let n = self.tasks.len();
        let indices = indices.unwrap_or_else(|| (0..n).collect());
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
            let first = st.venv.reset_some(&resets).map_err(value_error)?;
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
        actions: PyArrayLike2<'py, f32, AllowTypeChange>,
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
            let slots = st.venv.step_flat(&flat, mask.as_deref()).map_err(value_error)?;
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

// ------------------------------------------------------------------------------------------------
// Policies
// ------------------------------------------------------------------------------------------------

/// A prompt, as the policy feeds it: states normalised with the run's statistics, returns-to-go
/// divided by its scale. Made by `Policy.task_prompt`, `Policy.prompt` or `Policy.eval_plan`.
#[pyclass(module = "promptdt._native", frozen)]
struct Prompt {
    inner: SegmentBatch,
}

#[pymethods]
impl Prompt {
    /// Steps in the prompt (J x H).
    #[getter]
    fn steps(&self) -> usize {
        self.inner.steps
    }
    /// `[steps, obs_dim]` float32, normalised.
    #[getter]
    fn states<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let b = &self.inner;
        array2(py, b.states.clone(), b.steps, b.state_dim)
    }
    /// `[steps, act_dim]` float32.
    #[getter]
    fn actions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let b = &self.inner;
        array2(py, b.actions.clone(), b.steps, b.act_dim)
    }
    /// `[steps]` float32, divided by the run's return scale.
    #[getter]
    fn returns_to_go<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f32>> {
        self.inner.returns_to_go.clone().into_pyarray(py)
    }
    /// `[steps]` int64.
    #[getter]
    fn timesteps<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        self.inner.timesteps.clone().into_pyarray(py)
    }
    /// `[steps]` float32: 1 for real steps, 0 for padding.
    #[getter]
    fn mask<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f32>> {
        self.inner.mask.clone().into_pyarray(py)
    }
    fn __repr__(&self) -> String {
        format!(
            "Prompt(steps={}, obs_dim={}, act_dim={})",
            self.inner.steps, self.inner.state_dim, self.inner.act_dim
        )
    }
}

/// What `promptdt eval` draws for one task: the prompt its episodes share and their reset seeds.
#[pyclass(module = "promptdt._native", frozen, get_all)]
struct TaskPlan {
    /// `cheetah_vel-2`
    name: String,
    /// The task's index in its family.
    index: usize,
    /// Reset seed of each episode.
    seeds: Vec<u64>,
    /// None for the methods without a prompt.
    prompt: Option<Py<Prompt>>,
}

#[pymethods]
impl TaskPlan {
    fn __repr__(&self) -> String {
        format!(
            "TaskPlan(name={:?}, index={}, episodes={})",
            self.name,
            self.index,
            self.seeds.len()
        )
    }
}

struct PolicyState {
    run: pdt_policy::Policy,
    /// The keys and values of the distinct prompts set (`None`: no prompt set), and the row of
    /// each episode (one row: every episode).
    prefix: Option<(PrefixCache, Vec<i64>)>,
    /// One per episode (its history, last action and checks); `None` until its first
    /// observation.
    episodes: Vec<Option<Episode>>,
    /// The first return token of the episodes (`reset`'s target return).
    target: Target,
}

/// A trained run's prompted policy, acting in a batch of episodes as `promptdt eval` does.
#[pyclass(module = "promptdt._native", frozen)]
struct Policy {
    state: Mutex<PolicyState>,
    #[pyo3(get)]
    obs_dim: usize,
    #[pyo3(get)]
    act_dim: usize,
    /// History length K.
    #[pyo3(get)]
    k: usize,
    #[pyo3(get)]
    method: String,
    /// The run's environment family.
    #[pyo3(get)]
    env: String,
    #[pyo3(get)]
    uses_prompt: bool,
    #[pyo3(get)]
    target_return: f32,
    #[pyo3(get)]
    rtg_scale: f32,
    #[pyo3(get)]
    max_ep_len: usize,
    /// Iteration of the checkpoint loaded.
    #[pyo3(get)]
    iteration: u64,
    /// Steps of a prompt drawn from the run's data.
    #[pyo3(get)]
    prompt_steps: usize,
}

/// What `act` does with an episode: start it at its first observation, or record its step.
enum Next {
    Start(pdt_policy::Observation),
    Step(pdt_policy::Step),
}

impl Policy {
    fn batch_prefix(st: &PolicyState, n: usize) -> PyResult<Option<PrefixCache>> {
        if !st.run.method.uses_prompt() {
            return Ok(None);
        }
        let Some((cache, rows)) = &st.prefix else {
            return Err(value_error("this run's method takes a prompt: call set_prompt first"));
        };
        let rows: Vec<i64> = match rows.len() {
            1 => vec![rows[0]; n],
            m if m == n => rows.clone(),
            m => {
                return Err(value_error(format!(
                    "{m} prompts were set for {n} episodes: give one prompt, or one per episode"
                )))
            }
        };
        let index = Tensor::from_slice(&rows).to_device(st.run.device);
        Ok(Some(cache.select(&index)))
    }
}

#[pymethods]
impl Policy {
    /// Loads the latest checkpoint of the run in `run_dir` (a directory `promptdt train` wrote).
    /// `device`: "cpu", "cuda", "cuda:N" or "auto"; `data`: where the run's data are now, if they
    /// moved (needed only for `task_prompt` and `eval_plan`); `threads`: libtorch threads (None:
    /// libtorch's default).
    #[staticmethod]
    #[pyo3(signature = (run_dir, device = "cpu", data = None, threads = None))]
    fn load(
        py: Python<'_>,
        run_dir: PathBuf,
        device: &str,
        data: Option<PathBuf>,
        threads: Option<usize>,
    ) -> PyResult<Self> {
        existing(&run_dir, "run directory")?;
        let device: pdt_model::device::DeviceSpec = device.parse().map_err(value_error)?;
        if let Some(t) = threads {
            if t == 0 {
                return Err(value_error("threads must be at least 1"));
            }
            tch::set_num_threads(t as i32);
        }
        let run = py
            .detach(|| {
                pdt_policy::Policy::load(&run_dir, Some(device), data.as_deref())
                    .map_err(|e| e.to_string())
            })
            .map_err(value_error)?;
        let target = run.target(None).map_err(value_error)?;
        Ok(Self {
            obs_dim: run.stats.obs_dim,
            act_dim: run.stats.act_dim,
            k: run.k,
            method: run.method.name().to_string(),
            env: run.env.clone(),
            uses_prompt: run.method.uses_prompt(),
            target_return: run.stats.target_return,
            rtg_scale: run.stats.rtg_scale,
            max_ep_len: run.max_ep_len(),
            iteration: run.iteration,
            prompt_steps: run.prompt_steps,
            state: Mutex::new(PolicyState { run, prefix: None, episodes: Vec::new(), target }),
        })
    }

    /// The tasks whose prompts `task_prompt` can draw (test tasks first).
    fn prompt_tasks(&self) -> PyResult<Vec<usize>> {
        lock(&self.state)?.run.prompt_tasks().map_err(value_error)
    }

    /// A prompt of task `task` drawn from the run's prompt set as the evaluation draws one.
    #[pyo3(signature = (task, seed = 0))]
    fn task_prompt(&self, task: usize, seed: u64) -> PyResult<Prompt> {
        let st = lock(&self.state)?;
        Ok(Prompt { inner: st.run.task_prompt(task, seed).map_err(value_error)? })
    }

    /// A prompt from a demonstration's arrays: raw states `[n, obs_dim]`, actions `[n, act_dim]`,
    /// raw returns-to-go `[n]` (not divided by the scale) and timesteps `[n]`.
    fn prompt(
        &self,
        states: PyArrayLike2<'_, f64, AllowTypeChange>,
        actions: PyArrayLike2<'_, f64, AllowTypeChange>,
        returns_to_go: PyArrayLike1<'_, f64, AllowTypeChange>,
        timesteps: PyArrayLike1<'_, i64, AllowTypeChange>,
    ) -> PyResult<Prompt> {
        let rows = |a: &PyArrayLike2<'_, f64, AllowTypeChange>| -> Vec<Vec<f64>> {
            a.as_array().rows().into_iter().map(|r| r.to_vec()).collect()
        };
        let arrays = PromptArrays {
            states: rows(&states),
            actions: rows(&actions),
            returns_to_go: returns_to_go.as_array().to_vec(),
            timesteps: timesteps.as_array().to_vec(),
        };
        let st = lock(&self.state)?;
        // The prompt's largest inputs are not kept: an episode names its own when its action is
        // refused.
        let mut inputs = Inputs::default();
        Ok(Prompt { inner: st.run.prompt_from_arrays(&arrays, &mut inputs).map_err(value_error)? })
    }

    /// What `promptdt eval --split SPLIT --episodes N` draws for each task, in its order. Acting
    /// on all of them together (one environment per seed, task by task, each episode with its
    /// task's prompt) takes the evaluation's actions and returns.
    #[pyo3(signature = (split = "test", episodes = None))]
    fn eval_plan(
        &self,
        py: Python<'_>,
        split: &str,
        episodes: Option<usize>,
    ) -> PyResult<Vec<TaskPlan>> {
        let plan = lock(&self.state)?.run.eval_plan(split, episodes).map_err(value_error)?;
        plan.into_iter()
            .map(|t| {
                let prompt = t.prompt.map(|p| Py::new(py, Prompt { inner: p })).transpose()?;
                Ok(TaskPlan { name: t.name, index: t.index, seeds: t.seeds, prompt })
            })
            .collect()
    }

    /// Sets the prompt: one `Prompt` for every episode, or a list with one per episode. The
    /// distinct prompts' keys and values are computed once, together, as the evaluator does.
    fn set_prompt(&self, py: Python<'_>, prompt: &Bound<'_, PyAny>) -> PyResult<()> {
        let items: Vec<Bound<'_, Prompt>> = match prompt.cast::<Prompt>() {
            Ok(p) => vec![p.clone()],
            Err(_) => prompt.extract().map_err(|_| {
                value_error("set_prompt takes a Prompt or a list of Prompts (one per episode)")
            })?,
        };
        if items.is_empty() {
            return Err(value_error("set_prompt: the list of prompts is empty"));
        }
        // Distinct prompt objects, in order of first appearance, and each episode's row.
        let mut distinct: Vec<&Bound<'_, Prompt>> = Vec::new();
        let mut rows = Vec::with_capacity(items.len());
        for p in &items {
            let row = match distinct.iter().position(|d| d.is(p)) {
                Some(r) => r,
                None => {
                    distinct.push(p);
                    distinct.len() - 1
                }
            };
            rows.push(row as i64);
        }
        let batches: Vec<&SegmentBatch> = distinct.iter().map(|p| &p.get().inner).collect();
        let mut st = lock(&self.state)?;
        if !st.run.method.uses_prompt() {
            return Err(value_error(format!(
                "this run's method ({}) takes no prompt",
                self.method
            )));
        }
        if let Some(b) =
            batches.iter().find(|b| b.state_dim != self.obs_dim || b.act_dim != self.act_dim)
        {
            return Err(value_error(format!(
                "prompt dims {}/{} differ from the policy's {}/{}",
                b.state_dim, b.act_dim, self.obs_dim, self.act_dim
            )));
        }
        // `&mut` to hand the (Send, not Sync) policy to the GIL-free closure.
        let run = &mut st.run;
        let cache = py
            .detach(move || run.prefix(&batches).map_err(|e| e.to_string()))
            .map_err(value_error)?;
        st.prefix = Some((cache, rows));
        Ok(())
    }

    /// Starts `n_episodes` new episodes (the next `act` takes their first observations), aiming
    /// at `target_return` (None: the run's G*).
    #[pyo3(signature = (n_episodes, target_return = None))]
    fn reset(&self, n_episodes: usize, target_return: Option<f64>) -> PyResult<()> {
        if n_episodes == 0 {
            return Err(value_error("n_episodes must be at least 1"));
        }
        let mut st = lock(&self.state)?;
        st.target = st.run.target(target_return).map_err(value_error)?;
        st.episodes = vec![None; n_episodes];
        Ok(())
    }

    /// Restarts the given episodes (e.g. those an environment reset): their next observation is
    /// a first one.
    fn restart(&self, episodes: Vec<usize>) -> PyResult<()> {
        let mut st = lock(&self.state)?;
        let n = st.episodes.len();
        for &i in &episodes {
            let slot =
                st.episodes.get_mut(i).ok_or_else(|| value_error(format!("episode {i} of {n}")))?;
            *slot = None;
        }
        Ok(())
    }

    /// The next action of every episode, `[n, act_dim]` float32. `obs`: `[n, obs_dim]` raw
    /// observations; `reward`: `[n]`, the rewards the last actions earned (ignored for episodes at
    /// their first observation, required for the others).
    #[pyo3(signature = (obs, reward = None))]
    fn act<'py>(
        &self,
        py: Python<'py>,
        obs: PyArrayLike2<'py, f64, AllowTypeChange>,
        reward: Option<PyArrayLike1<'py, f64, AllowTypeChange>>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let obs = obs.as_array();
        let reward: Option<Vec<f64>> = reward.map(|r| r.as_array().to_vec());
        let mut guard = lock(&self.state)?;
        let st = &mut *guard;
        let n = st.episodes.len();
        if n == 0 {
            return Err(value_error("call reset(n_episodes) before act"));
        }
        if obs.shape() != [n, self.obs_dim] {
            return Err(value_error(format!(
                "obs: shape {:?}, expected [{n}, {}] (episodes, obs_dim)",
                obs.shape(),
                self.obs_dim
            )));
        }
        if let Some(r) = &reward {
            if r.len() != n {
                return Err(value_error(format!("reward: {} values for {n} episodes", r.len())));
            }
        }
        // Check everything before changing any episode, so an error leaves the state as it was.
        let at = |i: usize| move |e: PolicyError| value_error(format!("episode {i}: {e}"));
        let mut steps = Vec::with_capacity(n);
        for (i, row) in obs.rows().into_iter().enumerate() {
            let o = st.run.observation(&row.to_vec()).map_err(at(i))?;
            let Some(e) = &st.episodes[i] else {
                steps.push(Next::Start(o));
                continue;
            };
            let r = match &reward {
                None => {
                    return Err(value_error(format!(
                        "episode {i} is under way: pass the rewards of the last actions"
                    )))
                }
                Some(r) => r[i],
            };
            let step = st.run.step(r, o).map_err(at(i))?;
            match st.run.check(e, &step) {
                Err(PolicyError::EpisodeFull { max_ep_len }) => {
                    return Err(value_error(format!(
                        "episode {i} has reached the model's max_ep_len ({max_ep_len} steps): reset or restart it"
                    )))
                }
                Err(e) => return Err(at(i)(e)),
                Ok(()) => steps.push(Next::Step(step)),
            }
        }
        let prefix = Self::batch_prefix(st, n)?;
        let starts: Vec<bool> = steps.iter().map(|s| matches!(s, Next::Start(_))).collect();
        let target = st.target;
        for (slot, next) in st.episodes.iter_mut().zip(steps) {
            match (slot, next) {
                (Some(e), Next::Step(step)) => st.run.record(e, step).map_err(value_error)?,
                (slot, Next::Start(o)) => *slot = Some(st.run.start(o, target)),
                (None, Next::Step(_)) => return Err(value_error("internal: a step of no episode")),
            }
        }
        let flat = {
            // `&mut` to hand the (Send, not Sync) policy to the GIL-free closure.
            let st: &mut PolicyState = st;
            py.detach(move || {
                let eps: Vec<&Episode> = st.episodes.iter().flatten().collect();
                st.run.act(&eps, prefix.as_ref()) // [n * da]
            })
        };
        let da = self.act_dim;
        // An action that is not finite (inputs each representable can still overflow inside the
        // model) refuses the whole call: every episode goes back to where it was before it.
        let bad = flat.chunks_exact(da).position(|a| a.iter().any(|x| !x.is_finite()));
        if let Some(b) = bad {
            let mut why = None;
            for (i, (slot, a)) in st.episodes.iter_mut().zip(flat.chunks_exact(da)).enumerate() {
                let Some(e) = slot else { continue };
                if i == b {
                    why = e.accept(a).err();
                } else {
                    e.take_back();
                }
                // An episode started by this call is not started.
                if starts[i] {
                    *slot = None;
                }
            }
            let why = why.map_or_else(String::new, |e| e.to_string());
            return Err(value_error(format!(
                "episode {b}: {why}. The call is refused and every episode is as it was before it"
            )));
        }
        for (slot, a) in st.episodes.iter_mut().zip(flat.chunks_exact(da)) {
            if let Some(e) = slot {
                e.accept(a).map_err(value_error)?;
            }
        }
        array2(py, flat, n, da)
    }

    /// Returns so far of each episode (None before its first observation).
    fn episode_returns(&self) -> PyResult<Vec<Option<f64>>> {
        Ok(lock(&self.state)?.episodes.iter().map(|e| e.as_ref().map(Episode::ret)).collect())
    }

    fn __repr__(&self) -> String {
        format!(
            "Policy(method={:?}, env={:?}, obs_dim={}, act_dim={}, k={}, iteration={})",
            self.method, self.env, self.obs_dim, self.act_dim, self.k, self.iteration
        )
    }
}

// ------------------------------------------------------------------------------------------------
// Runs: the CLI's library calls
// ------------------------------------------------------------------------------------------------

/// `promptdt train`: trains from `config` (a TOML file) into `out`, or resumes the run in `out`
/// (`resume=True`). Returns `{"dir", "iterations_done", "finished", "last_test_mean"}`.
#[pyfunction]
#[pyo3(signature = (out, config = None, resume = false, seed = None, iterations = None, method = None, device = None, data = None))]
#[allow(clippy::too_many_arguments)]
fn train<'py>(
    py: Python<'py>,
    out: PathBuf,
    config: Option<PathBuf>,
    resume: bool,
    seed: Option<u64>,
    iterations: Option<u64>,
    method: Option<String>,
    device: Option<&str>,
    data: Option<PathBuf>,
) -> PyResult<Bound<'py, PyDict>> {
    use pdt_train::config::{Method, Overrides, TrainConfig};
    let device: Option<pdt_model::device::DeviceSpec> =
        device.map(str::parse).transpose().map_err(value_error)?;
    let cfg = match (resume, &config) {
        (true, Some(_)) => return Err(value_error("give config or resume=True, not both")),
        (true, None) => None,
        (false, None) => return Err(value_error("give config (a TOML file) or resume=True")),
        (false, Some(path)) => {
            existing(path, "config")?;
            let mut cfg = TrainConfig::from_file(path).map_err(value_error)?;
            let method = method
                .as_deref()
                .map(str::parse::<Method>)
                .transpose()
                .map_err(|e| value_error(format!("method {e}")))?;
            let overrides = Overrides {
                seed,
                iterations,
                method,
                device,
                data: data.clone(),
                ..Overrides::default()
            };
            // No MACAW preset here: the environment is never asked.
            cfg.apply(&overrides, |_| Ok::<usize, std::convert::Infallible>(0))
                .map_err(value_error)?;
            Some(cfg)
        }
    };
    let summary = py
        .detach(|| {
            let mut progress = |_: &pdt_train::run::Progress| {};
            let opts = pdt_train::run::TrainOptions {
                resume,
                resume_with: pdt_train::run::ResumeWith { iterations, device, data: data.clone() },
                stop_after_iterations: None,
                progress: &mut progress,
            };
            pdt_train::run::train(cfg, &out, opts).map_err(|e| e.to_string())
        })
        .map_err(value_error)?;
    let d = PyDict::new(py);
    d.set_item("dir", summary.dir)?;
    d.set_item("iterations_done", summary.iterations_done)?;
    d.set_item("finished", summary.finished)?;
    let mean = summary
        .last_test
        .map(|t| t.iter().map(|r| r.return_mean).sum::<f64>() / t.len().max(1) as f64);
    d.set_item("last_test_mean", mean)?;
    Ok(d)
}

/// `promptdt eval`: the final evaluation of a run's latest checkpoint (written to the run's
/// `eval_final.json`); returns that file's content as JSON text.
#[pyfunction]
#[pyo3(signature = (run_dir, episodes = None, split = "test", device = None, data = None))]
fn evaluate(
    py: Python<'_>,
    run_dir: PathBuf,
    episodes: Option<usize>,
    split: &str,
    device: Option<&str>,
    data: Option<PathBuf>,
) -> PyResult<String> {
    existing(&run_dir, "run directory")?;
    let device: Option<pdt_model::device::DeviceSpec> =
        device.map(str::parse).transpose().map_err(value_error)?;
    let r = py
        .detach(|| {
            pdt_train::run::evaluate_run(&run_dir, episodes, split, device, data.as_deref())
                .map_err(|e| e.to_string())
        })
        .map_err(value_error)?;
    serde_json::to_string(&r).map_err(value_error)
}

/// `promptdt reproduce --list`: every committed experiment with its cells and its cost per budget,
/// as JSON text (a list of `{name, title, cells, pending, budgets: [{budget, runs, iterations,
/// hours, note}]}`).
#[pyfunction]
fn experiments() -> PyResult<String> {
    let list = pdt_repro::list().map_err(value_error)?;
    let v: Vec<serde_json::Value> = list
        .iter()
        .map(|e| {
            let budgets: Vec<serde_json::Value> = e
                .budgets
                .iter()
                .map(|b| {
                    serde_json::json!({
                        "budget": b.budget, "runs": b.runs, "iterations": b.iterations,
                        "hours": b.hours, "note": b.note,
                    })
                })
                .collect();
            serde_json::json!({
                "name": e.name, "title": e.title, "cells": e.cells, "pending": e.pending,
                "budgets": budgets,
            })
        })
        .collect();
    serde_json::to_string(&v).map_err(value_error)
}

/// Whether `family` (any spelling [`pdt_envs::family`] takes) collects its datasets with scripted
/// policies ([`collect_scripted`]) rather than from an RL agent ([`collect_from_agent`]).
#[pyfunction]
fn is_scripted(family: &str) -> PyResult<bool> {
    Ok(pdt_envs::family(family).map_err(value_error)?.scripted().is_some())
}

/// `promptdt collect --env FAMILY` for a family with scripted policies: the scripted
/// expert/medium/random datasets and prompt sets of the family's default tasks, into `out`.
/// `action_noise`: the expert's noise where the family takes one (Meta-World reach: standard
/// deviation; default 0.2, 0 = deterministic).
#[pyfunction]
#[pyo3(signature = (family, out, seed = 0, episodes = None, prompt_episodes = None, action_noise = None))]
fn collect_scripted(
    py: Python<'_>,
    family: &str,
    out: PathBuf,
    seed: u64,
    episodes: Option<usize>,
    prompt_episodes: Option<usize>,
    action_noise: Option<f64>,
) -> PyResult<usize> {
    use pdt_envs::collect_scripted::{CollectConfig, ScriptedFamily};
    let fam = pdt_envs::family(family).map_err(value_error)?;
    let scripted = fam.scripted().ok_or_else(|| {
        let names: Vec<&str> = ScriptedFamily::ALL.iter().map(|f| f.name()).collect();
        value_error(format!(
            "{family} has no scripted policies ({} do); use collect_from_agent",
            names.join(", ")
        ))
    })?;
    let mut cfg = CollectConfig::for_family(scripted);
    cfg.seed = seed;
    if let Some(e) = episodes {
        cfg.episodes_per_task = e;
    }
    if let Some(e) = prompt_episodes {
        cfg.prompt_episodes = e;
    }
    if let Some(n) = action_noise {
        if !scripted.takes_action_noise() {
            let names: Vec<&str> = ScriptedFamily::ALL
                .iter()
                .filter(|f| f.takes_action_noise())
                .map(|f| f.name())
                .collect();
            return Err(value_error(format!("action_noise is for {}", names.join(", "))));
        }
        cfg.reach_action_noise = n;
    }
    let summary = py
        .detach(|| pdt_envs::collect_scripted::collect(&cfg, &out, &mut |_, _| {}))
        .map_err(value_error)?;
    Ok(summary.entries.len() * 2)
}

/// `promptdt collect --env FAMILY --from-pretrained`: datasets and prompt sets of a MuJoCo family
/// from a committed agent directory (`pretrained/<family>`), into `out`.
#[pyfunction]
#[pyo3(signature = (agent_dir, out, seed = 0, episodes = None, prompt_episodes = None, device = "cpu"))]
fn collect_from_agent(
    py: Python<'_>,
    agent_dir: PathBuf,
    out: PathBuf,
    seed: u64,
    episodes: Option<usize>,
    prompt_episodes: Option<usize>,
    device: &str,
) -> PyResult<usize> {
    existing(&agent_dir, "agent directory")?;
    let spec: pdt_model::device::DeviceSpec = device.parse().map_err(value_error)?;
    let device = pdt_model::device::resolve(spec).map_err(value_error)?;
    let mut cfg = pdt_rl::datasets::DatasetConfig { seed, ..Default::default() };
    if let Some(e) = episodes {
        cfg.episodes = e;
    }
    if let Some(e) = prompt_episodes {
        cfg.prompt_episodes = e;
    }
    let summary = py
        .detach(|| pdt_rl::datasets::generate(&agent_dir, &out, &cfg, device, &mut |_, _| {}))
        .map_err(value_error)?;
    Ok(summary.entries.len())
}

/// The Rust environment benchmark (`pdt_envs::bench`, no Python in the loop), for comparison with
/// the same stepping from Python: JSON text of its results.
#[pyfunction]
#[pyo3(signature = (families, steps_per_env, vec_envs, threads, seed = 0))]
fn bench_envs(
    py: Python<'_>,
    families: Vec<String>,
    steps_per_env: usize,
    vec_envs: usize,
    threads: Vec<usize>,
    seed: u64,
) -> PyResult<String> {
    let cfg = pdt_envs::bench::EnvBenchConfig { families, steps_per_env, vec_envs, threads, seed };
    let r = py.detach(|| pdt_envs::bench::run(&cfg)).map_err(value_error)?;
    serde_json::to_string(&r).map_err(value_error)
}

/// Sets libtorch's intra-op threads for this process.
#[pyfunction]
fn set_num_threads(threads: usize) -> PyResult<()> {
    if threads == 0 {
        return Err(value_error("threads must be at least 1"));
    }
    tch::set_num_threads(threads as i32);
    Ok(())
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("LIBTORCH_VERSION", "2.11.0")?;
    m.add_function(wrap_pyfunction!(load_dataset, m)?)?;
    m.add_function(wrap_pyfunction!(write_dataset, m)?)?;
    m.add_function(wrap_pyfunction!(families, m)?)?;
    m.add_function(wrap_pyfunction!(task_params, m)?)?;
    m.add_function(wrap_pyfunction!(train, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(collect_scripted, m)?)?;
    m.add_function(wrap_pyfunction!(is_scripted, m)?)?;
    m.add_function(wrap_pyfunction!(experiments, m)?)?;
    m.add_function(wrap_pyfunction!(collect_from_agent, m)?)?;
    m.add_function(wrap_pyfunction!(set_num_threads, m)?)?;
    m.add_function(wrap_pyfunction!(bench_envs, m)?)?;
    m.add_class::<VecEnv>()?;
    m.add_class::<Policy>()?;
    m.add_class::<Prompt>()?;
    m.add_class::<TaskPlan>()?;
    Ok(())
}
