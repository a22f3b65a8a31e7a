//! Runs: the CLI's library calls (train, evaluate, collect, list experiments, benchmark).

use crate::errors::Failure;
use crate::signals::{interruptible, interruptible_ticking, Progress};
use crate::{existing, lib_error, value_error};
use pdt_base::stop::StopFlag;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

/// The error of a long call stopped by Ctrl-C or by its progress callable: the callable's
/// exception when it raised one, else the library's (an `Interrupted` error, or a real failure).
fn stopped_or(progress: &Progress, e: Failure) -> PyErr {
    progress.take_error().unwrap_or_else(|| e.into_py())
}

/// `promptdt train`: trains from `config` (a TOML file) into `out`, or resumes the run in `out`
/// (`resume=True`). Returns `{"dir", "iterations_done", "finished", "last_test_mean"}`.
/// `progress`: called after every iteration with `{"iteration", "iterations", "loss",
/// "test_return", "elapsed_s"}`. Ctrl-C (or an exception of `progress`) stops it before the next
/// gradient step and raises; the run resumes from its last checkpoint or resume point.
/// `env`: a Python `factory(task)` making the environments of the run's evaluations
/// (`crate::factory`), in place of its family's (a suite's worker, or none: offline).
#[pyfunction]
#[pyo3(signature = (out, config = None, resume = false, seed = None, iterations = None, method = None, device = None, matmul = None, data = None, progress = None, env = None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn train<'py>(
    py: Python<'py>,
    out: PathBuf,
    config: Option<PathBuf>,
    resume: bool,
    seed: Option<u64>,
    iterations: Option<u64>,
    method: Option<String>,
    device: Option<&str>,
    matmul: Option<&str>,
    data: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
    env: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    use pdt_rundir::config::{Method, Overrides, TrainConfig};
    let device: Option<pdt_base::device::DeviceSpec> =
        device.map(str::parse).transpose().map_err(value_error)?;
    let matmul: Option<pdt_base::device::Matmul> =
        matmul.map(str::parse).transpose().map_err(|e| value_error(format!("matmul: {e}")))?;
    if resume && matmul.is_some() {
        return Err(value_error("matmul: not with resume=True (a run keeps its own)"));
    }
    let cfg = match (resume, &config) {
        (true, Some(_)) => return Err(value_error("give config or resume=True, not both")),
        (true, None) => None,
        (false, None) => return Err(value_error("give config (a TOML file) or resume=True")),
        (false, Some(path)) => {
            existing(path, "config")?;
            let mut cfg = TrainConfig::from_file(path).map_err(lib_error)?;
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
                matmul,
                data: data.clone(),
                ..Overrides::default()
            };
            // No MACAW preset here: the environment is never asked.
            cfg.apply(&overrides, |_| Ok::<usize, std::convert::Infallible>(0))
                .map_err(lib_error)?;
            Some(cfg)
        }
    };
    let envs = factory_envs(env);
    let interrupt = StopFlag::default();
    let report = Progress::new(progress, &interrupt);
    let started = std::time::Instant::now();
    let summary = interruptible(py, &interrupt, || {
        let mut progress = |p: &pdt_train::run::Progress| {
            report.report(|d| {
                d.set_item("iteration", p.iteration)?;
                d.set_item("iterations", p.iterations)?;
                d.set_item("loss", p.loss)?;
                d.set_item("test_return", p.test_return)?;
                d.set_item("elapsed_s", started.elapsed().as_secs_f64())
            })
        };
        let opts = pdt_train::run::TrainOptions {
            resume,
            resume_with: pdt_train::run::ResumeWith { iterations, device, data: data.clone() },
            stop_after_iterations: None,
            progress: &mut progress,
            interrupt: interrupt.clone(),
            envs: envs.clone(),
        };
        pdt_train::run::train(cfg, &out, opts).map_err(|e| Failure::of(&e))
    })?
    .map_err(|e| stopped_or(&report, e))?;
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

/// The environments a Python `factory(task)` makes, as the library's evaluations take them.
fn factory_envs(env: Option<Py<PyAny>>) -> Option<std::sync::Arc<dyn pdt_train::run::EnvMaker>> {
    env.map(|factory| {
        std::sync::Arc::new(crate::factory::FactoryEnvs { factory })
            as std::sync::Arc<dyn pdt_train::run::EnvMaker>
    })
}

/// `promptdt eval`: the final evaluation of a run's latest checkpoint (written to the run's
/// `eval_final.json`); returns that file's content as JSON text.
/// With `prompt_strategy` (or a test-time `prompt_episodes` / `prompt_length`) the evaluation
/// uses that strategy (docs/prompt-control.md), writes `eval_prompt_<strategy>.json` and returns
/// its content: the evaluation, `prompt_strategy` and the strategy's `picks`. With `adapt`
/// (`soft-prompt`, `ptdt`, `lora`; `adapt_steps` / `adapt_batch` its budget) each test task is
/// adapted first (`promptdt eval --adapt`): `eval_adapt_<kind>.json`, with `adapt` and each
/// task's `adapt_log`.
/// `progress`: called with `{"done", "total", "unit": "episodes", "elapsed_s"}` as episodes end
/// (at most every 50 ms); Ctrl-C (or an exception of `progress`) stops the episodes at their next
/// step and raises, and nothing is written.
/// `env`: a Python `factory(task)` making each episode's environment (`crate::factory`) in place
/// of the run's family's; the result is returned and not written (`evaluate_run_in`).
/// A run with no environment to act in (a suite without `[environment]`) and no `env` is
/// evaluated offline (`pdt_train::run::evaluate_run_offline`): `eval_offline.json`'s content.
#[pyfunction]
#[pyo3(signature = (run_dir, episodes = None, split = "test", device = None, data = None,
                    prompt_strategy = None, prompt_episodes = None, prompt_length = None,
                    adapt = None, adapt_steps = None, adapt_batch = None, progress = None,
                    env = None))]
#[allow(clippy::too_many_arguments)] // the keywords of `promptdt.evaluate`
pub(crate) fn evaluate(
    py: Python<'_>,
    run_dir: PathBuf,
    episodes: Option<usize>,
    split: &str,
    device: Option<&str>,
    data: Option<PathBuf>,
    prompt_strategy: Option<&str>,
    prompt_episodes: Option<usize>,
    prompt_length: Option<usize>,
    adapt: Option<&str>,
    adapt_steps: Option<usize>,
    adapt_batch: Option<usize>,
    progress: Option<Py<PyAny>>,
    env: Option<Py<PyAny>>,
) -> PyResult<String> {
    existing(&run_dir, "run directory")?;
    let envs = factory_envs(env);
    let adapt = match adapt {
        None => None,
        Some(kind) => {
            let d = pdt_rundir::config::AdaptConfig::default();
            Some(pdt_rundir::config::AdaptConfig {
                kind: kind.parse().map_err(lib_error)?,
                steps: adapt_steps.unwrap_or(d.steps),
                batch: adapt_batch.unwrap_or(d.batch),
                ..d
            })
        }
    };
    let device: Option<pdt_base::device::DeviceSpec> =
        device.map(str::parse).transpose().map_err(value_error)?;
    let prompt = match (prompt_strategy, prompt_episodes, prompt_length) {
        (None, None, None) => None,
        (name, episodes, length) => Some(pdt_prompt::PromptStrategy {
            strategy: name.unwrap_or("reference").parse().map_err(lib_error)?,
            episodes,
            length,
            ..Default::default()
        }),
    };
    // The evaluation asked for, at the test time read from the run (`asked_test_time`).
    let request = |test_time| pdt_train::run::EvalRequest {
        episodes,
        split: split.into(),
        device,
        data: data.clone(),
        test_time,
        repeats: 1,
    };
    // A run with no environment (a suite without `[environment]`) and no factory given plays
    // no episodes: its offline evaluation, `eval_offline.json`'s content (an action error).
    if envs.is_none() && pdt_train::run::evaluates_offline(&run_dir).map_err(lib_error)? {
        let (prompt, adapt) = (prompt.as_ref(), adapt.as_ref());
        let test_time = pdt_train::run::asked_test_time(&run_dir, data.as_deref(), prompt, adapt)
            .map_err(lib_error)?;
        let e = pdt_train::run::evaluate_run_offline(&run_dir, &request(test_time))
            .map_err(lib_error)?;
        return serde_json::to_string(&e).map_err(lib_error);
    }
    // The episodes end in the library's rollouts, which count them in the watch; the waiting
    // thread reports the count. `None`: the run's configuration is unreadable, which the
    // evaluation reports itself before any episode.
    let total = planned_episodes(&run_dir, episodes, split);
    let watch = pdt_envs::rollout::Watch::default();
    let report = Progress::new(progress, &watch.stop);
    let started = std::time::Instant::now();
    let mut shown = 0;
    let tick = || {
        let done = watch.episodes.get();
        if let (Some(total), true) = (total, done != shown) {
            shown = done;
            // An adaptation that scores candidates by their return plays more episodes than planned.
            let total = total.max(done);
            report.report(|d| progress_items(d, done, total, "episodes", started));
        }
    };
    let r = interruptible_ticking(py, &watch.stop, tick, || {
        pdt_envs::rollout::watching(&watch, || {
            // The strategy and adaptation asked for, as the evaluation's test time (read from
            // the run's configuration, whose errors this thread reports as the evaluation's).
            let (prompt, adapt, dir) = (prompt.as_ref(), adapt.as_ref(), &run_dir);
            let test_time = pdt_train::run::asked_test_time(dir, data.as_deref(), prompt, adapt)
                .map_err(|e| Failure::of(&e))?;
            pdt_train::run::evaluate_run_in(&run_dir, &request(test_time), envs.clone())
                .map_err(|e| Failure::of(&e))
        })
    })?
    .map_err(|e| stopped_or(&report, e))?;
    // The default strategy returns `eval_final.json`'s content, as before strategies.
    if r.prompt_strategy.is_default() && r.adapt.is_none() {
        serde_json::to_string(&r.eval).map_err(lib_error)
    } else {
        serde_json::to_string(&r).map_err(lib_error)
    }
}

/// The episodes an evaluation of the run in `dir` plays: each task of `split`, `episodes` (else
/// the run's `eval.episodes`) each; `None` where the run's configuration cannot be read.
fn planned_episodes(dir: &std::path::Path, episodes: Option<usize>, split: &str) -> Option<usize> {
    let cfg = pdt_rundir::config::TrainConfig::from_file(&dir.join("config.toml")).ok()?;
    let (train, test) = pdt_envs::family(&cfg.env.name).ok()?.split(&cfg.env.split).ok()?;
    let tasks = if split == "train" { train.len() } else { test.len() };
    Some(tasks * episodes.unwrap_or(cfg.eval.episodes))
}

/// `promptdt reproduce --list`: every committed experiment with its cells and its cost per budget,
/// as JSON text (a list of `{name, title, cells, pending, budgets: [{budget, runs, iterations,
/// hours, note}]}`).
#[pyfunction]
pub(crate) fn experiments() -> PyResult<String> {
    // The library's own struct, serialised: the fields are the library's, not a copy kept here.
    let list = pdt_repro::list().map_err(lib_error)?;
    serde_json::to_string(&list).map_err(lib_error)
}

/// Whether `family` (any spelling [`pdt_envs::family`] takes) collects its datasets with scripted
/// policies ([`collect_scripted`]) rather than from an RL agent ([`collect_from_agent`]).
#[pyfunction]
pub(crate) fn is_scripted(family: &str) -> PyResult<bool> {
    Ok(pdt_envs::family(family).map_err(lib_error)?.scripted().is_some())
}

/// `promptdt collect --env FAMILY` for a family with scripted policies: the scripted
/// expert/medium/random datasets and prompt sets of the family's default tasks, into `out`.
/// `action_noise`: the expert's noise where the family takes one (Meta-World reach: standard
/// deviation; default 0.2, 0 = deterministic). Returns the number of files written (a dataset and
/// a prompt set per task and mode). `progress`: called with `{"done", "total", "unit":
/// "episodes", "elapsed_s"}` as episodes are played (at most every 50 ms; datasets' and prompt
/// sets' episodes alike); Ctrl-C stops it between episodes and raises (the files written are
/// whole; the card is written only at the end).
#[pyfunction]
#[pyo3(signature = (family, out, seed = 0, episodes = None, prompt_episodes = None, action_noise = None, progress = None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn collect_scripted(
    py: Python<'_>,
    family: &str,
    out: PathBuf,
    seed: u64,
    episodes: Option<usize>,
    prompt_episodes: Option<usize>,
    action_noise: Option<f64>,
    progress: Option<Py<PyAny>>,
) -> PyResult<usize> {
    use pdt_envs::collect_scripted::{CollectConfig, ScriptedFamily};
    let fam = pdt_envs::family(family).map_err(lib_error)?;
    let scripted = fam.scripted().ok_or_else(|| {
        let names: Vec<&str> = ScriptedFamily::all().iter().map(|f| f.name()).collect();
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
            let names: Vec<&str> = ScriptedFamily::all()
                .iter()
                .filter(|f| f.takes_action_noise())
                .map(|f| f.name())
                .collect();
            return Err(value_error(format!("action_noise is for {}", names.join(", "))));
        }
        cfg.reach_action_noise = n;
    }
    let report = Progress::new(progress, &cfg.interrupt);
    let started = std::time::Instant::now();
    // The library reports whole files (a task's mode can take minutes: Meta-World's 200
    // episodes); its threads count episodes, which the waiting thread reports.
    let per_pair = cfg.episodes_per_task.saturating_add(cfg.prompt_episodes);
    let total = (cfg.tasks.len() * cfg.modes.len()).saturating_mul(per_pair);
    let mut shown = 0;
    let tick = || {
        let done = cfg.episodes_played.get();
        if done != shown {
            shown = done;
            report.report(|d| progress_items(d, done, total, "episodes", started));
        }
    };
    let summary = interruptible_ticking(py, &cfg.interrupt, tick, || {
        pdt_envs::collect_scripted::collect(&cfg, &out, &mut |_, _| {}).map_err(|e| Failure::of(&e))
    })?
    .map_err(|e| stopped_or(&report, e))?;
    // Each entry is one task's mode: its dataset and its prompt set.
    Ok(summary.entries.len() * 2)
}

/// `promptdt collect --env FAMILY --from-pretrained`: datasets and prompt sets of a MuJoCo family
/// from an agent directory (`pretrained/<family>`), into `out`. Returns the number of files
/// written. `progress`: called with `{"done", "total", "unit": "episodes", "elapsed_s"}` after
/// each chunk of episodes; Ctrl-C stops it between steps and raises (the files written are whole).
#[pyfunction]
#[pyo3(signature = (agent_dir, out, seed = 0, episodes = None, prompt_episodes = None, device = "cpu", progress = None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn collect_from_agent(
    py: Python<'_>,
    agent_dir: PathBuf,
    out: PathBuf,
    seed: u64,
    episodes: Option<usize>,
    prompt_episodes: Option<usize>,
    device: &str,
    progress: Option<Py<PyAny>>,
) -> PyResult<usize> {
    existing(&agent_dir, "agent directory")?;
    let spec: pdt_base::device::DeviceSpec = device.parse().map_err(value_error)?;
    let device = pdt_torch::device::resolve(spec).map_err(lib_error)?;
    let mut cfg = pdt_rl::datasets::DatasetConfig { seed, ..Default::default() };
    if let Some(e) = episodes {
        cfg.episodes = e;
    }
    if let Some(e) = prompt_episodes {
        cfg.prompt_episodes = e;
    }
    let report = Progress::new(progress, &cfg.interrupt);
    let started = std::time::Instant::now();
    let summary = interruptible(py, &cfg.interrupt, || {
        pdt_rl::datasets::generate(&agent_dir, &out, &cfg, device, &mut |done, total| {
            report.report(|d| progress_items(d, done, total, "episodes", started))
        })
        .map_err(|e| Failure::of(&e))
    })?
    .map_err(|e| stopped_or(&report, e))?;
    Ok(summary.files)
}

/// A collection's progress report.
fn progress_items(
    d: &Bound<'_, PyDict>,
    done: usize,
    total: usize,
    unit: &str,
    started: std::time::Instant,
) -> PyResult<()> {
    d.set_item("done", done)?;
    d.set_item("total", total)?;
    d.set_item("unit", unit)?;
    d.set_item("elapsed_s", started.elapsed().as_secs_f64())
}

/// The Rust environment benchmark (`pdt_envs::bench`, no Python in the loop), for comparison with
/// the same stepping from Python: JSON text of its results.
#[pyfunction]
#[pyo3(signature = (families, steps_per_env, vec_envs, threads, seed = 0))]
pub(crate) fn bench_envs(
    py: Python<'_>,
    families: Vec<String>,
    steps_per_env: usize,
    vec_envs: usize,
    threads: Vec<usize>,
    seed: u64,
) -> PyResult<String> {
    let cfg = pdt_envs::bench::EnvBenchConfig { families, steps_per_env, vec_envs, threads, seed };
    let r = py.detach(|| pdt_envs::bench::run(&cfg)).map_err(lib_error)?;
    serde_json::to_string(&r).map_err(lib_error)
}
