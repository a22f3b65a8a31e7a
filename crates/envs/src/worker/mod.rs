//! Environments that live outside this process: a user's gymnasium environments, made and stepped
//! by a Python worker process that the `promptdt` Python package provides (`python -m
//! promptdt.worker`). [`WorkerSpec`] is what a task suite's `[environment]` table declares about
//! them; [`make_batch`] starts a worker for a batch of episodes and returns them as a
//! [`VecEnv`] like any other, one request per vector reset or step (the framing:
//! `protocol.rs`; the protocol: `docs/your-own-tasks.md`).

mod backend;
mod process;
mod protocol;
mod spec;

pub use backend::{Acted, Resets};
pub use spec::{WorkerSpec, WorkerTask};

use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::vec_env::{EnvDims, StepSlot, VecEnv};
use crate::EnvError;

/// How requests reach the Python side that makes and steps the environments
/// (`promptdt.worker.Session`): a worker process, or the calling interpreter itself (the Python
/// package's `evaluate(env=factory)`, through pyo3). Whatever the transport, the requests, the
/// Python code answering them and the checks of the answers are the same, so an evaluation gives
/// the same numbers either way.
pub trait Transport: Send {
    /// Sends one frame (`header`: one line of JSON, without its end of line; `payload`: the f32
    /// values it announces) and returns the reply frame, waiting up to `timeout` where the
    /// transport can. `Err`: the transport itself failed (the message says how).
    fn call(
        &mut self,
        header: &str,
        payload: &[f32],
        timeout: Duration,
    ) -> Result<(String, Vec<f32>), String>;

    /// The other side is not to be asked again (it failed or answered nonsense): a worker
    /// process is killed. Nothing, by default.
    fn abandon(&mut self) {}
}

/// The variable naming the worker's Python when the spec names none.
pub const PYTHON_VAR: &str = "PROMPTDT_PYTHON";

/// The interpreter that runs `spec`'s worker: its `python` (relative to `dir`, the suite file's
/// directory), else `$PROMPTDT_PYTHON`, else `python3` on `PATH`.
pub fn python(spec: &WorkerSpec, dir: &Path) -> PathBuf {
    match &spec.python {
        Some(p) if p.is_relative() && p.components().count() > 1 => dir.join(p),
        Some(p) => p.clone(),
        None => default_python(),
    }
}

/// The Python where nothing names one: `$PROMPTDT_PYTHON`, else `python3` on `PATH`.
pub fn default_python() -> PathBuf {
    std::env::var_os(PYTHON_VAR).filter(|p| !p.is_empty()).map_or("python3".into(), PathBuf::from)
}

/// Starts a worker running `spec` and makes in it one environment per entry of `tasks` (the
/// task of each episode), all of sizes `dims` (the family's observation and action sizes and its
/// horizon, which cuts episodes that do not end by themselves). `dir` is the suite file's
/// directory: relative `python` paths start there, and it is first on the worker's `PYTHONPATH`.
/// The worker is killed when the returned [`VecEnv`] is dropped.
pub fn make_batch(
    spec: &WorkerSpec,
    dir: &Path,
    tasks: Vec<WorkerTask>,
    dims: EnvDims,
) -> Result<VecEnv, EnvError> {
    let n = tasks.len();
    if n == 0 {
        // Nothing to step: no interpreter to start.
        return Ok(VecEnv::new(Vec::new(), 1));
    }
    let envs = spawn(spec, dir, tasks, dims, serde_json::Value::Null)?;
    Ok(VecEnv::external(Box::new(envs), vec![dims; n]))
}

/// The worker process of `spec`, its environments made (and, for a collection, its `policies`
/// named).
fn spawn(
    spec: &WorkerSpec,
    dir: &Path,
    tasks: Vec<WorkerTask>,
    dims: EnvDims,
    policies: serde_json::Value,
) -> Result<backend::WorkerEnvs, EnvError> {
    let n = tasks.len();
    let all = |message: String| EnvError::Worker {
        task: format!("{n} episodes' environments"),
        step: None,
        message,
    };
    let step_timeout = Duration::try_from_secs_f64(spec.step_timeout_s)
        .ok()
        .filter(|t| !t.is_zero())
        .ok_or_else(|| {
            all(format!(
                "step_timeout_s = {} is not a positive number of seconds",
                spec.step_timeout_s
            ))
        })?;
    let process = process::Process::spawn(&python(spec, dir), dir).map_err(all)?;
    let spec = serde_json::to_value(spec).map_err(|e| all(e.to_string()))?;
    backend::WorkerEnvs::start(Box::new(process), spec, step_timeout, tasks, dims, policies)
}

/// In the caller's own interpreter a request cannot be timed out.
const NO_TIMEOUT: Duration = Duration::from_secs(u64::MAX / 4);

/// [`make_batch`] over another `transport`, whose Python side makes each task's environment with
/// a factory of its own (the `init` request carries no spec).
pub fn make_batch_over(
    transport: Box<dyn Transport>,
    tasks: Vec<WorkerTask>,
    dims: EnvDims,
) -> Result<VecEnv, EnvError> {
    let n = tasks.len();
    let null = serde_json::Value::Null;
    let envs = backend::WorkerEnvs::start(transport, null.clone(), NO_TIMEOUT, tasks, dims, null)?;
    Ok(VecEnv::external(Box::new(envs), vec![dims; n]))
}

/// Environments on the Python side together with policies that act in them: what a collection
/// from a Python policy steps (`crate::collect_policy`). Each reset or step may ask, per
/// environment, for a named policy's action on the new observation, which comes back in the
/// same reply: one request per vector step, as an evaluation's.
pub struct Acting {
    envs: backend::WorkerEnvs,
}

impl Acting {
    /// A worker process running `spec` (see [`make_batch`]), one environment per entry of
    /// `tasks`, and the policies `policies` names (`{"expert": "module:callable", ...}`).
    pub fn spawn(
        spec: &WorkerSpec,
        dir: &Path,
        tasks: Vec<WorkerTask>,
        dims: EnvDims,
        policies: &std::collections::BTreeMap<String, Option<String>>,
    ) -> Result<Self, EnvError> {
        Ok(Self { envs: spawn(spec, dir, tasks, dims, serde_json::json!(policies))? })
    }

    /// The same over another `transport`: its Python side makes the environments by `spec` when
    /// given, else by its own factory, and takes each policy named without an entry (`None`)
    /// from the callables it was given.
    pub fn over(
        transport: Box<dyn Transport>,
        spec: Option<&WorkerSpec>,
        tasks: Vec<WorkerTask>,
        dims: EnvDims,
        policies: &std::collections::BTreeMap<String, Option<String>>,
    ) -> Result<Self, EnvError> {
        let spec = serde_json::to_value(spec).map_err(|e| EnvError::Worker {
            task: "the environments".into(),
            step: None,
            message: e.to_string(),
        })?;
        let policies = serde_json::json!(policies);
        let envs = backend::WorkerEnvs::start(transport, spec, NO_TIMEOUT, tasks, dims, policies)?;
        Ok(Self { envs })
    }

    /// Resets each environment whose seed is given; for each whose `act` entry names a policy,
    /// also that policy's action on its first observation.
    pub fn reset(
        &mut self,
        seeds: &[Option<u64>],
        act: &[Option<String>],
    ) -> Result<(Resets, Vec<Acted>), EnvError> {
        self.envs.reset_acting(seeds, Some(act))
    }

    /// Steps the environments of `mask` with their rows of `actions` (`act_dim` values each, by
    /// environment); for each whose `act` entry names a policy and whose episode goes on (not
    /// ended, not at the horizon), also that policy's action on its new observation.
    pub fn step(
        &mut self,
        actions: &[f32],
        mask: &[bool],
        act: &[Option<String>],
    ) -> Result<(Vec<StepSlot>, Vec<Acted>), EnvError> {
        self.envs.step_acting(actions, mask, Some(act))
    }
}
