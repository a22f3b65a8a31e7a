//! `promptdt.evaluate(run, env=factory)`: an evaluation whose environments a Python factory makes
//! in the calling interpreter. The requests go to `promptdt.worker.Session(factory)` through
//! [`SessionTransport`] instead of a worker process's pipe; the rest, the Python answering them
//! and the Rust checking the answers (`pdt_envs::worker::make_batch_over`), is the worker's, so
//! an evaluation in a user's environment gives the same numbers from Python and from the CLI.

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray1};
use pdt_envs::vec_env::{EnvDims, VecEnv};
use pdt_envs::worker::{make_batch_over, Transport, WorkerTask};
use pdt_envs::{EnvError, EnvFamily};
use pyo3::prelude::*;
use std::time::Duration;

/// The frames of one batch of environments, answered by a `promptdt.worker.Session` in this
/// interpreter (taking the GIL for each request, as the evaluation runs on a thread of its own).
pub(crate) struct SessionTransport {
    session: Py<PyAny>,
}

impl SessionTransport {
    /// A new `promptdt.worker.Session(factory, policies)`: a collection's (`crate::collect`)
    /// policies by name, and the factory making its environments (`None`: the suite's
    /// `[environment]`, which `init` then carries).
    pub(crate) fn new(
        py: Python<'_>,
        factory: Option<Py<PyAny>>,
        policies: &Bound<'_, pyo3::types::PyDict>,
    ) -> PyResult<Self> {
        let class = py.import("promptdt.worker")?.getattr("Session")?;
        Ok(Self { session: class.call1((factory, policies))?.unbind() })
    }
}

impl Transport for SessionTransport {
    fn call(
        &mut self,
        header: &str,
        payload: &[f32],
        _timeout: Duration,
    ) -> Result<(String, Vec<f32>), String> {
        Python::attach(|py| {
            let sent = PyArray1::from_slice(py, payload);
            let reply = self.session.bind(py).call_method1("handle", (header, sent))?;
            let (header, values): (String, Option<PyReadonlyArray1<'_, f32>>) = reply.extract()?;
            let values = match values {
                None => Vec::new(),
                Some(v) => v.to_vec()?,
            };
            Ok((header, values))
        })
        // `Session.handle` answers the factory's and the environments' exceptions itself; what
        // reaches here escaped it (a `BaseException`, a reply of the wrong type).
        .map_err(|e: PyErr| format!("promptdt.worker.Session.handle raised {e}"))
    }
}

impl Drop for SessionTransport {
    fn drop(&mut self) {
        // The environments are closed when the evaluation is done with them, as a worker's are.
        Python::attach(|py| {
            if let Err(e) = self.session.bind(py).call_method0("close") {
                e.print(py);
            }
        });
    }
}

/// Makes each batch of an evaluation's environments by the Python `factory(task)` (`task`:
/// `{"index", "name", "params"}` of the run's family; of a suite, its task's name and `params`
/// table, what its worker gets).
pub(crate) struct FactoryEnvs {
    pub(crate) factory: Py<PyAny>,
}

impl pdt_train::run::EnvMaker for FactoryEnvs {
    fn make_batch(&self, family: &dyn EnvFamily, tasks: &[usize]) -> Result<VecEnv, EnvError> {
        let session = Python::attach(|py| -> PyResult<Py<PyAny>> {
            let class = py.import("promptdt.worker")?.getattr("Session")?;
            Ok(class.call1((self.factory.clone_ref(py),))?.unbind())
        })
        .map_err(|e| EnvError::Worker {
            task: format!("{} episodes' environments", tasks.len()),
            step: None,
            message: format!("promptdt.worker.Session: {e}"),
        })?;
        let tasks = tasks
            .iter()
            .map(|&index| match family.as_suite() {
                // A suite's task as its CLI worker gets it: its name and `params` table, so a
                // factory serves both ways of evaluating.
                Some(suite) => suite.worker_task(index),
                // Named as the evaluation names a built-in family's tasks (`family-index`).
                None => {
                    let name = format!("{}-{index}", family.name());
                    Ok(WorkerTask { index, name, params: family.task_params(index)? })
                }
            })
            .collect::<Result<Vec<_>, EnvError>>()?;
        let p = family.preset();
        let dims = EnvDims { obs_dim: p.obs_dim, act_dim: p.act_dim, horizon: p.horizon };
        make_batch_over(Box::new(SessionTransport { session }), tasks, dims)
    }
}
