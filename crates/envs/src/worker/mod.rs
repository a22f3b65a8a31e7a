//! Environments that live outside this process: a user's gymnasium environments, made and stepped
//! by a Python worker process that the `promptdt` Python package provides (`python -m
//! promptdt.worker`). [`WorkerSpec`] is what a task suite's `[environment]` table declares about
//! them; [`make_batch`] starts a worker for a batch of episodes and returns them as a
//! [`VecEnv`] like any other, one request per vector reset or step (the framing:
//! `protocol.rs`; the protocol: `docs/your-own-tasks-worker.md`).

mod backend;
mod process;
mod protocol;
mod spec;

pub use spec::{WorkerSpec, WorkerTask};

use std::path::{Path, PathBuf};

use crate::vec_env::{EnvDims, VecEnv};
use crate::EnvError;

/// The variable naming the worker's Python when the spec names none.
pub const PYTHON_VAR: &str = "PROMPTDT_PYTHON";

/// The interpreter that runs `spec`'s worker: its `python` (relative to `dir`, the suite file's
/// directory), else `$PROMPTDT_PYTHON`, else `python3` on `PATH`.
pub fn python(spec: &WorkerSpec, dir: &Path) -> PathBuf {
    match (&spec.python, std::env::var_os(PYTHON_VAR).filter(|p| !p.is_empty())) {
        (Some(p), _) if p.is_relative() && p.components().count() > 1 => dir.join(p),
        (Some(p), _) => p.clone(),
        (None, Some(p)) => PathBuf::from(p),
        (None, None) => PathBuf::from("python3"),
    }
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
    let envs = backend::WorkerEnvs::start(spec, &python(spec, dir), dir, tasks, dims)?;
    Ok(VecEnv::external(Box::new(envs), vec![dims; n]))
}
