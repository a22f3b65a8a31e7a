//! `promptdt.collect(suite, out, policy=...)`: a task suite's expert, medium and random datasets
//! collected in its environment from a Python policy, in this interpreter. The policy and the
//! environments answer the requests of `pdt_envs::collect_policy` through a
//! `promptdt.worker.Session` (`crate::factory::SessionTransport`), the code a worker process runs
//! for `promptdt collect --policy`, so both write the same bytes.

use crate::errors::Failure;
use crate::factory::SessionTransport;
use crate::signals::{interruptible_ticking, Progress};
use crate::{lib_error, value_error};
use pdt_data::mode::Mode;
use pdt_envs::collect_policy::{collect, PolicyCollectConfig, PolicySide};
use pdt_envs::suite::SuiteFamily;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

/// Collects `suite`'s datasets into `out` from `policy` (a callable `policy(obs, task)`;
/// `policy_name`, its `module:qualname`, is what the card records) and, for the medium level,
/// `medium_policy` or the expert with `medium_noise`. `factory(task)` makes each environment;
/// `None`: the suite's `[environment]`, made in this interpreter. Returns the number of files
/// written. Progress: `{"done", "total", "unit": "episodes", "elapsed_s"}`; Ctrl-C stops it
/// between vector steps (the files written are whole, the card is not written).
#[pyfunction]
#[pyo3(signature = (suite, out, policy, policy_name, medium_policy = None, medium_name = None,
                    factory = None, seed = 0, episodes = None, prompt_episodes = None,
                    modes = None, tasks = None, action_noise = None, medium_noise = None,
                    envs_per_task = None, progress = None))]
#[allow(clippy::too_many_arguments)] // the keywords of `promptdt.collect`
pub(crate) fn collect_policy(
    py: Python<'_>,
    suite: PathBuf,
    out: PathBuf,
    policy: Py<PyAny>,
    policy_name: String,
    medium_policy: Option<Py<PyAny>>,
    medium_name: Option<String>,
    factory: Option<Py<PyAny>>,
    seed: u64,
    episodes: Option<usize>,
    prompt_episodes: Option<usize>,
    modes: Option<Vec<String>>,
    tasks: Option<Vec<usize>>,
    action_noise: Option<f64>,
    medium_noise: Option<f64>,
    envs_per_task: Option<usize>,
    progress: Option<Py<PyAny>>,
) -> PyResult<usize> {
    let suite = SuiteFamily::load(&suite).map_err(lib_error)?;
    let mut cfg = PolicyCollectConfig::new(&suite, policy_name);
    cfg.seed = seed;
    cfg.medium = medium_name;
    if let Some(e) = episodes {
        cfg.episodes_per_task = e;
    }
    if let Some(n) = prompt_episodes {
        cfg.prompt_rule = format!("best:{n}").parse().map_err(value_error)?;
    }
    if let Some(m) = modes {
        cfg.modes =
            m.iter().map(|m| m.parse::<Mode>()).collect::<Result<_, _>>().map_err(value_error)?;
    }
    if let Some(t) = tasks {
        cfg.tasks = t;
    }
    if let Some(s) = action_noise {
        cfg.action_noise = s;
    }
    if let Some(s) = medium_noise {
        cfg.medium_noise = s;
    }
    if let Some(n) = envs_per_task {
        cfg.envs_per_task = n;
    }
    cfg.validate(&suite).map_err(lib_error)?;
    let policies = PyDict::new(py);
    policies.set_item("expert", policy)?;
    if let Some(m) = medium_policy {
        policies.set_item("medium", m)?;
    }
    let suite_environment = factory.is_none();
    let transport = SessionTransport::new(py, factory, &policies)?;
    let side = PolicySide::Given { transport: Box::new(transport), suite_environment };
    let report = Progress::new(progress, &cfg.interrupt);
    let started = std::time::Instant::now();
    let total = (cfg.tasks.len() * cfg.modes.len()).saturating_mul(cfg.episodes_per_task);
    let mut shown = 0;
    let tick = || {
        let done = cfg.episodes_played.get();
        if done != shown {
            shown = done;
            report.report(|d| {
                d.set_item("done", done)?;
                d.set_item("total", total)?;
                d.set_item("unit", "episodes")?;
                d.set_item("elapsed_s", started.elapsed().as_secs_f64())
            });
        }
    };
    let summary = interruptible_ticking(py, &cfg.interrupt, tick, || {
        collect(&suite, &cfg, side, &out, &mut |_, _| {}).map_err(|e| Failure::of(&e))
    })?
    .map_err(|e| report.take_error().unwrap_or_else(|| e.into_py()))?;
    Ok(summary.entries.len() * 2)
}
