//! The run loop, one for every method: a run directory created (or taken over to resume), then
//! iterations of the method's training steps with the reference's cadence of evaluations,
//! metrics and evaluation logs, checkpoints and resume points committed atomically, the batch
//! stream's position saved and restored, progress reported, and a stop after a given number of
//! iterations (an interruption, in tests). The method is a [`Learner`]; the directory's layout is
//! `docs/run-directory.md`.

use crate::error::{io_err, RunError};
use crate::methods::{
    self, CheckpointFiles, IterationAt, IterationMetrics, Learner, SavedSteps, TaskEval,
};
use crate::run_dir::{
    check_log_counts, commit_checkpoint, lock_run_dir, now_utc, remove_orphans, Log,
};
use crate::setup::{absolute, Setup, Split};
use crate::streams::torch_rng_lock;
use pdt_base::fs::write_atomic;
use pdt_base::seed::derive_seed;
use pdt_prompt::Rng;
use pdt_run::streams::STREAM_BATCHES;
use pdt_rundir::config::{TestTime, TrainConfig};
use pdt_rundir::{
    read_json, write_json, EvalLine, Latest, MetricsLine, PackInfo, RunDir, RunInfo, TrainState,
};
use pdt_rundir::{OfflineEvalLine, OfflineTaskResult, TaskResult};
use rand::SeedableRng;
use std::path::{Path, PathBuf};

/// Progress reported after every iteration.
#[derive(Debug, Clone)]
pub struct Progress {
    pub iteration: u64,
    pub iterations: u64,
    pub loss: f64,
    /// Average test return of the evaluation just made, if one was.
    pub test_return: Option<f64>,
}

/// How a call to [`train`] runs.
pub struct TrainOptions<'a> {
    /// Continue the run in the directory from its last checkpoint.
    pub resume: bool,
    /// With `resume`: what may change when a run goes on (nothing else may).
    pub resume_with: ResumeWith,
    /// Stop after this many iterations of this call (simulates an interruption in tests).
    pub stop_after_iterations: Option<u64>,
    pub progress: &'a mut dyn FnMut(&Progress),
    /// A request to stop now (a front end's Ctrl-C), checked before every gradient step: the call
    /// then returns [`RunError::Interrupted`] and writes nothing of the iteration under way, so
    /// the run resumes from its last checkpoint or resume point. Never set by default.
    pub interrupt: pdt_base::stop::StopFlag,
    /// The environments the run's evaluations play in, in place of its family's (`None`: the
    /// family's): the Python package's `train(..., env=factory)`. A task suite with no
    /// `[environment]` is then evaluated in them, not offline; a run resumes with evaluations of
    /// the kind it began with ([`check_same_evaluations`]).
    pub envs: Option<std::sync::Arc<dyn crate::evaluate::EnvMaker>>,
}

/// What may change when a run is resumed. Anything else (seed, method, data settings) would make
/// it another run; the CLI refuses those flags with `--resume`.
#[derive(Debug, Clone, Default)]
pub struct ResumeWith {
    /// Extend `train.iterations` (at least the iterations already done); written to `config.toml`.
    pub iterations: Option<u64>,
    /// Run on this device this time (the results of a CPU and a GPU run differ in rounding only).
    pub device: Option<pdt_base::device::DeviceSpec>,
    /// The data moved: read it from here; it must have the fingerprint the run recorded. Written
    /// to `config.toml`.
    pub data: Option<PathBuf>,
}

/// What a finished (or stopped) call did.
#[derive(Debug, Clone)]
pub struct TrainSummary {
    pub dir: PathBuf,
    pub iterations_done: u64,
    pub finished: bool,
    pub last_test: Option<Vec<TaskResult>>,
    /// The last offline evaluation of the held-out tasks (a run with no environment: the action
    /// error on their data, `pdt_eval::offline`), if there was one. Never a return.
    pub last_offline: Option<Vec<OfflineTaskResult>>,
    /// Why the run was not evaluated in an environment while it trained, if it was not
    /// ([`Setup::online_evaluation_note`]).
    pub note: Option<String>,
}

impl TrainSummary {
    /// The mean return over the held-out tasks at the last evaluation, if there was one.
    pub fn held_out_mean(&self) -> Option<f64> {
        let tasks = self.last_test.as_ref()?;
        Some(tasks.iter().map(|t| t.return_mean).sum::<f64>() / tasks.len().max(1) as f64)
    }
}

/// One line: where the run stopped, its last held-out return, its directory.
impl std::fmt::Display for TrainSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let state = if self.finished { "finished" } else { "stopped" };
        write!(f, "{state} after iteration {}", self.iterations_done)?;
        if let Some(mean) = self.held_out_mean() {
            write!(f, ", held-out average return {mean:.2}")?;
        }
        if let Some(tasks) = &self.last_offline {
            let mean = pdt_rundir::OfflineEval::mean_of(tasks);
            write!(f, ", held-out action MSE {mean:.4} (offline; lower is better)")?;
        }
        write!(f, ": {}", self.dir.display())?;
        if let Some(note) = &self.note {
            write!(f, " ({note})")?;
        }
        Ok(())
    }
}

/// The identity of a new run (`run.json`); `pack` where it trains in one.
fn run_info(setup: &Setup, loss_metric: &str, pack: Option<&PackInfo>) -> RunInfo {
    RunInfo {
        name: format!(
            "{}-{}-seed{}",
            setup.cfg.run.method.name(),
            setup.family.name(),
            setup.cfg.run.seed
        ),
        method: setup.cfg.run.method.name().into(),
        env: setup.family.name().into(),
        seed: setup.cfg.run.seed,
        task_split: setup.cfg.env.split.clone(),
        created: now_utc(),
        promptdt_version: env!("CARGO_PKG_VERSION").into(),
        loss_metric: Some(loss_metric.into()),
        pack: pack.cloned(),
    }
}

/// Trains from `cfg` into `dir` (created), or with `opts.resume`, continues the run in `dir` (its
/// `config.toml` is authoritative and `cfg` is ignored; `opts.resume_with` says what may change).
///
/// The directory has one owner: a second process on it gets an error, not interleaved files.
pub fn train(
    cfg: Option<TrainConfig>,
    dir: &Path,
    opts: TrainOptions<'_>,
) -> Result<TrainSummary, RunError> {
    let cfg = run_config_for(cfg, dir, opts.resume, &opts.resume_with)?;
    // Refuse before anything is written, each bad setting by name.
    cfg.validate()?;
    // Training computes as the run says, or not at all (`tf32` on the CPU is refused), before the
    // data are read.
    pdt_torch::device::set_matmul(pdt_torch::device::resolve(cfg.run.device)?, cfg.run.matmul)?;
    let toml = cfg.to_toml()?;
    let mut setup = Setup::new(cfg, dir)?;
    if let Some(maker) = opts.envs.clone() {
        setup.use_envs(dir, maker)?;
    }
    let _rng = torch_rng_lock();
    let threads = pdt_base::threads(setup.cfg.run.threads);
    tch::set_num_threads(threads as i32);
    // The learner (its model initialised from the seed) and its checks, before anything is written.
    let mut learner = methods::learner(&setup)?;
    learner.check_can_train()?;
    train_learner(&setup, &toml, dir, learner.as_mut(), opts, None)
}

/// Trains `learner` (its checks passed) of `setup` in `dir`: the directory created and owned,
/// its records written (`toml` as `config.toml`; `pack` in `run.json`) or checked, then the loop.
/// A pack's runs come here each with its member learner (`pdt-pack`).
pub fn train_learner(
    setup: &Setup,
    toml: &str,
    dir: &Path,
    learner: &mut dyn Learner,
    opts: TrainOptions<'_>,
    pack: Option<&PackInfo>,
) -> Result<TrainSummary, RunError> {
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let _owner = lock_run_dir(dir)?;
    prepare_run_dir(setup, dir, opts.resume, toml, learner.loss_metric(), pack)?;
    run_loop(setup, dir, learner, opts)
}

/// The configuration a call to [`train`] runs: `cfg` for a new run (its data directory made
/// absolute), the run's `config.toml` with `opts.resume_with`'s changes to resume.
pub fn run_config_for(
    cfg: Option<TrainConfig>,
    dir: &Path,
    resume: bool,
    with: &ResumeWith,
) -> Result<TrainConfig, RunError> {
    Ok(match (resume, cfg) {
        (true, _) => {
            let path = dir.join("config.toml");
            if !path.is_file() {
                // `run.json` is written first: with it and no `config.toml`, a `train` was killed
                // while creating the directory, before anything that could resume it was written.
                if dir.join("checkpoints").join("latest.json").exists() {
                    return Err(RunError::invalid(
                        dir.display(),
                        format!(
                            "{} is missing, but the run has a checkpoint: restore config.toml \
                             from a copy of the run (it cannot be guessed), or delete the run",
                            path.display()
                        ),
                    ));
                }
                if dir.join("run.json").is_file() {
                    return Err(RunError::invalid(
                        format!("run directory {}", dir.display()),
                        format!(
                            "interrupted while being created: it has run.json but no \
                             config.toml, so there is nothing to resume; delete it or rerun \
                             `promptdt train --config <experiment> --out {}`",
                            dir.display()
                        ),
                    ));
                }
                return Err(RunError::invalid(
                    dir.display(),
                    "no run to resume here (no config.toml)",
                ));
            }
            let mut c = TrainConfig::from_file(&path)?;
            if let Some(n) = with.iterations {
                c.train.iterations = n;
            }
            if let Some(d) = with.device {
                c.run.device = d;
            }
            if let Some(d) = &with.data {
                c.data.dir = absolute(d);
            }
            c
        }
        (false, Some(mut c)) => {
            // Recorded absolute, so the run evaluates and resumes the same way from any directory.
            c.data.dir = absolute(&c.data.dir);
            if pdt_envs::suite::is_suite_path(&c.env.name) {
                if let Some(p) = absolute(Path::new(&c.env.name)).to_str() {
                    c.env.name = p.to_owned();
                }
            }
            c
        }
        (false, None) => {
            return Err(RunError::invalid(
                "the run's configuration",
                "none given, and not resuming",
            ))
        }
    })
}

/// Makes the owned directory `dir` ready to train in: what a killed writer left removed, a new
/// run's records written (`run.json`, `config.toml` as `toml`, `task_stats.json`), or a resumed
/// run's checked against the data now.
fn prepare_run_dir(
    setup: &Setup,
    dir: &Path,
    resume: bool,
    toml: &str,
    loss_metric: &str,
    pack: Option<&PackInfo>,
) -> Result<(), RunError> {
    // Temporary files of a killed writer (we own the directory, so none is live).
    for d in [dir.to_path_buf(), dir.join("checkpoints")] {
        pdt_base::fs::remove_stale_temps(&d).map_err(io_err(&d))?;
    }
    let run = RunDir::at(dir);
    let has_checkpoint = run.latest_path().exists();
    if resume && !run.stats_path().exists() && !has_checkpoint {
        // Killed while the directory was being created (after `config.toml`): nothing was trained
        // from it, so what is missing is recreated from the configuration and data, exactly as a
        // new run writes it, and the run starts.
        if !run.info_path().is_file() {
            run.write_info(&run_info(setup, loss_metric, pack))?;
        }
        write_suite_copy(setup, &run)?;
        run.write_stats(&setup.run_data.stats)?;
    } else if resume {
        let recorded = pdt_run::files::read_stats(&run)?;
        setup.run_data.stats.check_same_as(&recorded).map_err(|m| {
            let dir = setup.cfg.data.dir.display();
            RunError::invalid(
                run.stats_path().display(),
                format!(
                    "{m}; data.dir is {dir}. Resume with the data the run trained on (--data DIR \
                     where it moved)"
                ),
            )
        })?;
    } else {
        if has_checkpoint {
            return Err(RunError::invalid(
                dir.display(),
                "already holds a run; use --resume to continue it or pick another --out",
            ));
        }
        run.write_info(&run_info(setup, loss_metric, pack))?;
        // Before `config.toml`: a run's configuration never names a suite the run has no copy of.
        write_suite_copy(setup, &run)?;
        let config = run.config_path();
        write_atomic(&config, toml.as_bytes()).map_err(io_err(&config))?;
        run.write_stats(&setup.run_data.stats)?;
    }
    // Checkpoint files a killed run left unreferenced (owning the directory makes this safe).
    remove_orphans(&run.checkpoints_dir())?;
    Ok(())
}

/// A run on a task suite keeps the suite file as it read it (`suite.toml`): the run evaluates,
/// serves and resumes from it without the original, and an edited original is refused
/// ([`pdt_envs::family_of_run`]).
fn write_suite_copy(setup: &Setup, run: &RunDir) -> Result<(), RunError> {
    let (Some(suite), path) = (setup.family.as_suite(), run.suite_path()) else { return Ok(()) };
    if path.exists() {
        return Ok(()); // the run's own copy: the family was read from it (`Setup::new`)
    }
    write_atomic(&path, suite.text().as_bytes()).map_err(io_err(&path))
}

/// The `eval.jsonl` lines of an evaluation on `eval_on` ("test" or "train"), with the learner's
/// adaptation columns and each task's target return ([`Setup::task_target_return`]).
fn eval_lines(
    setup: &Setup,
    res: &[TaskEval],
    iteration: u64,
    step: u64,
    eval_on: &str,
) -> Vec<EvalLine> {
    res.iter()
        .map(|r| {
            let target = setup.task_target_return(r.result.task_index);
            EvalLine {
                adaptation: r.adaptation,
                ..EvalLine::new(&r.result, iteration, step, eval_on, target)
            }
        })
        .collect()
}

/// Trains `learner` in the run directory `dir` (owned, its records written or checked by
/// [`train`]) from its last checkpoint with `opts.resume`, else from the start.
fn run_loop(
    setup: &Setup,
    dir: &Path,
    learner: &mut dyn Learner,
    opts: TrainOptions<'_>,
) -> Result<TrainSummary, RunError> {
    let cfg = &setup.cfg;
    let with = &opts.resume_with;
    let state = if opts.resume { load_checkpoint(dir, setup, learner)? } else { None };
    let (mut iteration, mut step) = state.as_ref().map_or((0, 0), |s| (s.iteration, s.step));
    if opts.resume && with.iterations.is_some() && iteration > cfg.train.iterations {
        return Err(RunError::invalid(
            format!("--iterations {}", cfg.train.iterations),
            format!(
                "the run in {} has already done {iteration} iterations; give at least that many \
                 to extend it",
                dir.display()
            ),
        ));
    }
    let run = RunDir::at(dir);
    let mut metrics = Log::open(
        run.metrics_path(),
        run.metrics_csv_path(),
        state.as_ref().map_or(0, |s| s.metrics_lines),
    )?;
    let mut evals = Log::open(
        run.eval_path(),
        run.eval_csv_path(),
        state.as_ref().map_or(0, |s| s.eval_lines),
    )?;
    // A run with no environment evaluates offline instead, into a log of its own (never
    // `eval.jsonl`: an action error is not a return). Other runs have no such file.
    let evaluates_offline = setup.evaluates_offline();
    let mut offline = match evaluates_offline {
        true => Some(Log::open(
            run.offline_eval_path(),
            run.offline_eval_csv_path(),
            state.as_ref().map_or(0, |s| s.offline_eval_lines),
        )?),
        false => None,
    };
    let mut last_offline = None;
    record_resume_changes(dir, cfg, with, opts.resume)?;
    let mut batch_rng = Rng::seed_from_u64(derive_seed(cfg.run.seed, STREAM_BATCHES, 0));
    if let Some(s) = &state {
        let pos = s.batch_rng_word_pos.parse::<u128>().map_err(|e| RunError::Corrupt {
            path: dir.join("checkpoints"),
            message: format!("batch_rng_word_pos: {e}"),
        })?;
        batch_rng.set_word_pos(pos);
    }
    let (t, started) = (&cfg.train, std::time::Instant::now());
    let mut last_test = None;
    // The run's own test time, the same at every evaluation.
    let test_time = TestTime::of(&setup.cfg);
    let note = setup.online_evaluation_note();
    let mut done_here = 0;
    while iteration < t.iterations {
        if opts.interrupt.is_set() {
            return Err(RunError::Interrupted { dir: dir.into(), iteration: iteration + 1 });
        }
        if opts.stop_after_iterations.is_some_and(|n| done_here >= n) {
            return Ok(TrainSummary {
                dir: dir.into(),
                iterations_done: iteration,
                finished: false,
                last_test,
                last_offline,
                note,
            });
        }
        let at = IterationAt {
            dir,
            iteration: iteration + 1,
            first_step: step,
            steps: t.steps_per_iteration,
            interrupt: &opts.interrupt,
        };
        let IterationMetrics { loss, mut columns } = learner.train_iteration(at, &mut batch_rng)?;
        step += t.steps_per_iteration;
        iteration += 1;
        done_here += 1;
        columns.insert(learner.loss_metric().into(), loss);
        let elapsed_s = metrics.elapsed_before + started.elapsed().as_secs_f64();
        metrics.append(&[MetricsLine { iteration, step, elapsed_s, values: columns }])?;
        let last = iteration == t.iterations;
        let mut test_return = None;
        // Reference: evaluation after the first iteration and every `interval` after it.
        let evaluates = note.is_none();
        if evaluates && ((iteration - 1) % t.test_eval_interval == 0 || last) {
            let mut rng = setup.eval_rng(Split::Test, iteration);
            let res = learner.evaluate(Split::Test, &test_time, &mut rng)?.tasks;
            evals.append(&eval_lines(setup, &res, iteration, step, "test"))?;
            let res: Vec<TaskResult> = res.into_iter().map(|r| r.result).collect();
            test_return =
                Some(res.iter().map(|r| r.return_mean).sum::<f64>() / res.len().max(1) as f64);
            last_test = Some(res);
        }
        if let Some(log) =
            offline.as_mut().filter(|_| (iteration - 1) % t.test_eval_interval == 0 || last)
        {
            // The same stream and counter as an evaluation in an environment would draw from.
            let mut rng = setup.eval_rng(Split::Test, iteration);
            if let Some(res) = learner.offline_evaluate(Split::Test, &mut rng)? {
                let lines: Vec<OfflineEvalLine> = res
                    .iter()
                    .map(|r| OfflineEvalLine {
                        iteration,
                        step,
                        eval_on: "test".into(),
                        result: r.clone(),
                    })
                    .collect();
                log.append(&lines)?;
                last_offline = Some(res);
            }
        }
        let train_evals = t.train_eval_interval > 0 && evaluates;
        if train_evals && ((iteration - 1) % t.train_eval_interval == 0 || last) {
            let mut rng = setup.eval_rng(Split::Train, iteration);
            let res = learner.evaluate(Split::Train, &test_time, &mut rng)?.tasks;
            evals.append(&eval_lines(setup, &res, iteration, step, "train"))?;
        }
        let keep = iteration % t.save_interval == 0 || last;
        if keep || (t.resume_interval > 0 && iteration % t.resume_interval == 0) {
            let state = TrainState {
                method: learner.state_tag().map(str::to_string),
                iteration,
                step,
                batch_rng_word_pos: batch_rng.get_word_pos().to_string(),
                adam_steps: serde_json::Value::Null,
                metrics_lines: metrics.lines,
                eval_lines: evals.lines,
                offline_eval_lines: offline.as_ref().map_or(0, |l| l.lines),
                keep,
            };
            save_checkpoint(dir, learner, state)?;
        }
        (opts.progress)(&Progress { iteration, iterations: t.iterations, loss, test_return });
    }
    Ok(TrainSummary {
        dir: dir.into(),
        iterations_done: iteration,
        finished: true,
        last_test,
        last_offline,
        note,
    })
}

/// Refuses to resume a run with evaluations of another kind than it began with: a task suite with
/// no `[environment]` is evaluated offline (`offline_eval.jsonl`, action errors), or in the
/// environments a caller gives (`eval.jsonl`, returns); one run's log never switches between them.
fn check_same_evaluations(setup: &Setup, dir: &Path, s: &TrainState) -> Result<(), RunError> {
    let offline_now = setup.evaluates_offline();
    let (why, how) = match (offline_now, s.eval_lines, s.offline_eval_lines) {
        (true, n, _) if n > 0 => (
            format!("its evaluations so far were played in environments given to it ({n} lines of eval.jsonl), and none are given now"),
            "resume it with the same environments (promptdt.train(out, resume=True, env=factory))",
        ),
        (false, _, n) if n > 0 => (
            format!("it was evaluated offline so far ({n} lines of offline_eval.jsonl), and environments are given now"),
            "resume it without env=, or train a new run with the environments",
        ),
        _ => return Ok(()),
    };
    Err(RunError::invalid(format!("run directory {}", dir.display()), format!("{why}: {how}")))
}

/// On resume with a longer run or moved data, what changed goes on record in `config.toml` (the
/// device is this invocation's only).
pub(crate) fn record_resume_changes(
    dir: &Path,
    cfg: &TrainConfig,
    with: &ResumeWith,
    resume: bool,
) -> Result<(), RunError> {
    if resume && (with.iterations.is_some() || with.data.is_some()) {
        let run = RunDir::at(dir);
        let mut recorded = run.config()?;
        recorded.train.iterations = cfg.train.iterations;
        recorded.data.dir.clone_from(&cfg.data.dir);
        run.write_config(&recorded)?;
    }
    Ok(())
}

/// The files of the checkpoint at `step` in `ck`.
pub(crate) fn checkpoint_files(ck: &Path, step: u64) -> CheckpointFiles {
    CheckpointFiles {
        weights: ck.join(Latest::model_name(step)),
        moments: ck.join(Latest::state_name(step)),
        state: ck.join(format!("state_{step}.json")),
    }
}

/// Saves weights, optimiser state and the training state; `latest.json` is written last, so a
/// crash before it leaves the previous checkpoint in force.
fn save_checkpoint(
    dir: &Path,
    learner: &mut dyn Learner,
    mut state: TrainState,
) -> Result<(), RunError> {
    let ck = dir.join("checkpoints");
    std::fs::create_dir_all(&ck).map_err(io_err(&ck))?;
    let files = checkpoint_files(&ck, state.step);
    state.adam_steps = learner.save(&files)?;
    write_json(&files.state, &state)?;
    let latest = Latest {
        step: state.step,
        iteration: state.iteration,
        model: Latest::model_name(state.step),
        state: Latest::state_name(state.step),
        keep: state.keep,
    };
    commit_checkpoint(&ck, latest)
}

/// The checkpoint in force, checked against its state file and the logs, restored into
/// `learner`; `None` when the run has none yet.
fn load_checkpoint(
    dir: &Path,
    setup: &Setup,
    learner: &mut dyn Learner,
) -> Result<Option<TrainState>, RunError> {
    let ck = dir.join("checkpoints");
    let latest_path = ck.join("latest.json");
    if !latest_path.exists() {
        return Ok(None);
    }
    let latest: Latest = read_json(&latest_path)?;
    let corrupt = |path: &Path, message: String| RunError::Corrupt { path: path.into(), message };
    // The files of a checkpoint are named by its step; anything else (another step's weights, a
    // path outside the directory) is refused rather than resumed from.
    let (model, opt) = (Latest::model_name(latest.step), Latest::state_name(latest.step));
    if latest.model != model || latest.state != opt {
        return Err(corrupt(
            &latest_path,
            format!(
                "names `{}` and `{}` for step {}; expected `{model}` and `{opt}`",
                latest.model, latest.state, latest.step
            ),
        ));
    }
    let files = checkpoint_files(&ck, latest.step);
    let state: TrainState = read_json(&files.state)?;
    let per = setup.cfg.train.steps_per_iteration;
    if state.method.as_deref() != learner.state_tag()
        || state.step != latest.step
        || state.iteration != latest.iteration
        || state.step != state.iteration.saturating_mul(per)
    {
        let method = state.method.as_deref().map_or_else(String::new, |m| format!("method {m} "));
        return Err(corrupt(
            &files.state,
            format!(
                "{method}iteration {} step {}, but latest.json says iteration {} step {} (and \
                 train.steps_per_iteration = {per})",
                state.iteration, state.step, latest.iteration, latest.step
            ),
        ));
    }
    // Before the counts: a switch of evaluation kind would read as a corrupt state file there.
    check_same_evaluations(setup, dir, &state)?;
    check_log_counts(&files.state, &state, &setup.eval_schedule())?;
    learner.load(&files, SavedSteps { step: state.step, adam_steps: &state.adam_steps })?;
    Ok(Some(state))
}
