//! `promptdt eval` of a run with no environment to act in (a task suite without `[environment]`):
//! the offline evaluation of its latest checkpoint (`pdt_eval::offline`, the prompted model's
//! action error on the tasks' data), written to `eval_offline.json`, apart from every file of
//! returns.

use crate::error::RunError;
use crate::evaluate::{check_recorded_stats, repeat_counter, EvalRequest};
use crate::methods;
use crate::setup::{Setup, Split};
use crate::streams::torch_rng_lock;
use pdt_run::files::{latest_checkpoint, run_config};
use pdt_rundir::{OfflineEval, RunDir, OFFLINE_MEASURE, OFFLINE_METRIC};
use std::path::Path;

/// Whether the run in `dir` is evaluated offline: its family (as the run trained on it) has no
/// environment to act in. Reads its configuration and suite only, no data.
pub fn evaluates_offline(dir: &Path) -> Result<bool, RunError> {
    let run = RunDir::at(dir);
    let cfg = run_config(&run, None, None)?;
    let family = pdt_envs::family_of_run(&cfg.env.name, &run.suite_path())?;
    Ok(family.as_suite().is_some_and(|s| s.environment().is_none()))
}

/// The offline evaluation of the latest checkpoint of the run in `dir` on `req.split`'s tasks
/// (`eval.offline_segments` segments each), drawn from the stream a final evaluation in an
/// environment draws from; written to `eval_offline.json`. The settings of episodes (`episodes`,
/// `test_time`, `repeats`) are refused: an offline evaluation plays none.
pub fn evaluate_run_offline(dir: &Path, req: &EvalRequest) -> Result<OfflineEval, RunError> {
    let refuse = |flag: &str| -> Result<OfflineEval, RunError> {
        Err(RunError::invalid(
            flag,
            format!(
                "the run in {} is evaluated offline (its suite declares no [environment]: the \
                 action error on the tasks' data), which plays no episodes",
                dir.display()
            ),
        ))
    };
    if req.episodes.is_some() {
        return refuse("episodes");
    }
    if req.test_time.is_some() {
        return refuse("a prompt strategy or adaptation");
    }
    if req.repeats != 1 {
        return refuse("repeats");
    }
    let which = match req.split.as_str() {
        "test" => Split::Test,
        "train" => Split::Train,
        other => {
            return Err(RunError::invalid("split", format!("unknown `{other}` (test or train)")))
        }
    };
    let run = RunDir::at(dir);
    let cfg = run_config(&run, req.device, req.data.as_deref())?;
    let setup = Setup::new(cfg, dir)?;
    check_recorded_stats(&setup, &run)?;
    let _rng = torch_rng_lock();
    let mut learner = methods::learner(&setup)?;
    let latest = latest_checkpoint(&run)?;
    learner.load_weights(&run.checkpoint_file(&latest.model))?;
    let mut rng = setup.eval_rng(which, repeat_counter(latest.iteration, 0));
    let tasks = learner.offline_evaluate(which, &mut rng)?.ok_or_else(|| {
        RunError::invalid(
            format!("run.method = \"{}\"", setup.cfg.run.method.name()),
            "has no offline evaluation (the action error of a prompted sequence model), and \
             the run's suite declares no [environment] to evaluate it in",
        )
    })?;
    let out = OfflineEval {
        metric: OFFLINE_METRIC.into(),
        measure: OFFLINE_MEASURE.into(),
        iteration: latest.iteration,
        step: latest.step,
        checkpoint: format!("checkpoints/{}", latest.model),
        eval_on: req.split.clone(),
        segments_per_task: setup.cfg.eval.offline_segments,
        mean_action_mse: OfflineEval::mean_of(&tasks),
        tasks,
    };
    run.write_offline_final(&out)?;
    Ok(out)
}
