//! The final evaluation of a run (`promptdt eval`): its latest checkpoint, loaded into the run's
//! learner, evaluated on its test (or training) tasks from a stream apart from training's, and
//! written to `eval_final.json`.

use crate::error::RunError;
use crate::methods;
use crate::setup::{Setup, Split};
use crate::streams::torch_rng_lock;
use pdt_envs::vec_env::VecEnv;
use pdt_envs::{ActionBounds, Env, EnvError, EnvFamily, EnvPreset};
use pdt_prompt::PromptStrategy;
use pdt_run::files::{latest_checkpoint, read_stats, run_config};
use pdt_rundir::config::{AdaptConfig, Adaptation, TestTime};
use pdt_rundir::{EvalRepeats, FinalEval, PromptEval, RunDir};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// What an evaluation of a run may change of the run's own (`promptdt eval`'s flags; each
/// `None` or default: the run's).
#[derive(Debug, Clone)]
pub struct EvalRequest {
    /// Episodes per task.
    pub episodes: Option<usize>,
    /// `test` (the held-out tasks) or `train`.
    pub split: String,
    pub device: Option<pdt_base::device::DeviceSpec>,
    /// Where the run's data are now, if they moved.
    pub data: Option<PathBuf>,
    /// What the evaluation does at test time (`None`: the run's own, [`TestTime::of`] its
    /// configuration): another prompt strategy, an `[eval.adapt]` adaptation, or the run's own
    /// adaptation with another budget (`TestTime::with_settings`, `Adaptation::with_budget`).
    /// Its settings are checked as the run's own would be; one the run's method cannot have is
    /// refused (`TestTime::apply_to`).
    pub test_time: Option<TestTime>,
    /// Independent repeats of the evaluation (`--repeats`; 1: one evaluation, as before).
    pub repeats: usize,
}

impl Default for EvalRequest {
    fn default() -> Self {
        Self {
            episodes: None,
            split: "test".into(),
            device: None,
            data: None,
            test_time: None,
            repeats: 1,
        }
    }
}

/// Repeat r of a final evaluation draws from the evaluation stream at `u64::MAX - iteration -
/// r x REPEAT_STRIDE`: repeat 0 is the evaluation without repeats, and no repeat's counter meets
/// a training evaluation's (the iteration, below 2^40) or another repeat's.
const REPEAT_STRIDE: u64 = 1 << 40;

/// The counter of repeat `r`'s evaluation stream (see [`REPEAT_STRIDE`]).
pub(crate) fn repeat_counter(iteration: u64, r: usize) -> u64 {
    u64::MAX - iteration - (r as u64) * REPEAT_STRIDE
}

/// Evaluates the latest checkpoint of the run in `dir` on its test tasks (or train tasks).
pub fn evaluate_run(
    dir: &Path,
    episodes: Option<usize>,
    split: &str,
    device: Option<pdt_base::device::DeviceSpec>,
    data: Option<&Path>,
) -> Result<FinalEval, RunError> {
    let req = EvalRequest {
        episodes,
        split: split.into(),
        device,
        data: data.map(Path::to_path_buf),
        test_time: None,
        repeats: 1,
    };
    evaluate_run_as(dir, &req).map(|e| e.eval)
}

/// The test time of an evaluation of the run in `dir` (its data in `data` if they moved) with
/// another prompt strategy or `[eval.adapt]` adaptation, each `None` for the run's own
/// ([`TestTime::with_settings`] of its configuration); `None` when neither is given.
pub fn asked_test_time(
    dir: &Path,
    data: Option<&Path>,
    prompt: Option<&PromptStrategy>,
    adapt: Option<&AdaptConfig>,
) -> Result<Option<TestTime>, RunError> {
    if prompt.is_none() && adapt.is_none() {
        return Ok(None);
    }
    let cfg = run_config(&RunDir::at(dir), None, data)?;
    Ok(Some(TestTime::with_settings(&cfg, prompt, adapt)))
}

/// The evaluation of the run in `dir` that `req` asks for. The default strategy without an
/// adaptation writes `eval_final.json`, as before strategies; another strategy writes
/// `eval_prompt_<strategy>.json` ([`PromptEval`], with its choices), an adaptation
/// `eval_adapt_<kind>.json` with each task's adaptation log, leaving `eval_final.json` to the
/// reference rule.
pub fn evaluate_run_as(dir: &Path, req: &EvalRequest) -> Result<PromptEval, RunError> {
    evaluate_run_in(dir, req, None)
}

/// Makes the environments of a batch of episodes in place of the run's family
/// ([`EnvFamily::make_batch`]): a caller's own environments, e.g. the Python package's
/// `evaluate(run, env=factory)`, whose factory's environments answer through
/// `pdt_envs::worker::make_batch_over`.
pub trait EnvMaker: Send + Sync {
    /// The environments of episodes of the run's family `family`, environment `i` one of task
    /// `tasks[i]` (the family's index).
    fn make_batch(&self, family: &dyn EnvFamily, tasks: &[usize]) -> Result<VecEnv, EnvError>;
}

/// [`evaluate_run_as`], the episodes played in the environments `envs` makes when given. Such an
/// evaluation writes no file: what the run directory records is what `promptdt eval` reproduces
/// from the run alone, and a caller's environments are not part of the run (its result is
/// returned only).
pub fn evaluate_run_in(
    dir: &Path,
    req: &EvalRequest,
    envs: Option<Arc<dyn EnvMaker>>,
) -> Result<PromptEval, RunError> {
    let EvalRequest { episodes, split, device, data, test_time, repeats } = req;
    if !(1..=1000).contains(repeats) {
        return Err(RunError::invalid("repeats", format!("= {repeats}: must be in 1..=1000")));
    }
    let (episodes, split, device, data) = (*episodes, split.as_str(), *device, data.as_deref());
    let run = RunDir::at(dir);
    let mut cfg = run_config(&run, device, data)?;
    if let Some(e) = episodes {
        cfg.eval.episodes = e;
    }
    // Written into the configuration as the run's own: `Setup::new` checks its settings as a
    // run's, and the files below are named from it.
    if let Some(t) = test_time {
        t.apply_to(&mut cfg).map_err(|e| RunError::invalid(dir.display(), e))?;
    }
    let mut setup = Setup::new(cfg, dir)?;
    let write = envs.is_none();
    if let Some(maker) = envs {
        setup.use_envs(dir, maker)?;
    }
    // On a GPU, as the run's own evaluations computed; on the CPU products are fp32 whatever the
    // run trained with (its checkpoints stay usable there).
    if setup.device.is_cuda() {
        pdt_torch::device::set_matmul(setup.device, setup.cfg.run.matmul)?;
    }
    check_recorded_stats(&setup, &run)?;
    let which = match split {
        "test" => Split::Test,
        "train" => Split::Train,
        other => {
            return Err(RunError::invalid("split", format!("unknown `{other}` (test or train)")))
        }
    };
    let _rng = torch_rng_lock();
    let mut learner = methods::learner(&setup)?;
    let test_time = TestTime::of(&setup.cfg);
    let latest = latest_checkpoint(&run)?;
    learner.load_weights(&run.checkpoint_file(&latest.model))?;
    // A stream apart from training's evaluations, so the final numbers are not a repeat of the log.
    let mut rng = setup.eval_rng(which, repeat_counter(latest.iteration, 0));
    let methods::Evaluation { tasks, picks, adapt_log } =
        learner.evaluate(which, &test_time, &mut rng)?;
    let tasks: Vec<_> = tasks.into_iter().map(|t| t.result).collect();
    let mean_return = tasks.iter().map(|r| r.return_mean).sum::<f64>() / tasks.len().max(1) as f64;
    let repeats = match *repeats {
        1 => None,
        n => {
            let mut rows = vec![tasks.iter().map(|t| t.return_mean).collect::<Vec<f64>>()];
            for r in 1..n {
                // From the checkpoint again: each repeat is the evaluation of the saved weights.
                learner.load_weights(&run.checkpoint_file(&latest.model))?;
                let mut rng = setup.eval_rng(which, repeat_counter(latest.iteration, r));
                let e = learner.evaluate(which, &test_time, &mut rng)?;
                rows.push(e.tasks.iter().map(|t| t.result.return_mean).collect());
            }
            let stream = match which {
                Split::Test => pdt_run::streams::STREAM_EVAL_TEST,
                Split::Train => pdt_run::streams::STREAM_EVAL_TRAIN,
            };
            let streams = format!(
                "repeat r: derive_seed(run seed {}, stream {stream}, 2^64 - 1 - iteration {} - r \
                 x 2^40); repeat 0 is the evaluation without --repeats",
                setup.cfg.run.seed, latest.iteration
            );
            Some(EvalRepeats::of(streams, rows))
        }
    };
    let result = FinalEval {
        repeats,
        adaptation: test_time.adaptation().and_then(Adaptation::recorded),
        iteration: latest.iteration,
        step: latest.step,
        checkpoint: format!("checkpoints/{}", latest.model),
        eval_on: split.into(),
        tasks,
        mean_return,
    };
    let prompt_strategy = setup.cfg.eval.prompt.clone();
    // Training tasks are not adapted: their file is the strategy's.
    let adapt =
        if which == Split::Test { setup.cfg.eval.adapt.clone() } else { Default::default() };
    let out = PromptEval { eval: result, prompt_strategy, picks, adapt, adapt_log };
    if !write {
        // Returned only (see `evaluate_run_in`).
    } else if out.prompt_strategy.is_default() && out.adapt.is_none() {
        run.write_final_eval(&out.eval)?;
    } else {
        run.write_prompt_eval(&out)?;
    }
    Ok(out)
}

/// Refuses data other than those the run trained on (their statistics and fingerprints against
/// `task_stats.json`), naming the file and the data directory.
pub(crate) fn check_recorded_stats(setup: &Setup, run: &RunDir) -> Result<(), RunError> {
    let stats_path = run.stats_path();
    let recorded = read_stats(run)?;
    setup.run_data.stats.check_same_as(&recorded).map_err(|m| {
        let dir = setup.cfg.data.dir.display();
        RunError::invalid(
            stats_path.display(),
            format!(
                "{m}; data.dir is {dir}. Evaluate with the data the run trained on (--data DIR \
                 where it moved)"
            ),
        )
    })
}

impl Setup {
    /// The run's evaluations play in the environments `maker` makes, in place of its family's
    /// (which keeps all else: tasks, splits, constants). A task suite with no `[environment]`
    /// is then evaluated in them like any family, not offline.
    pub(crate) fn use_envs(
        &mut self,
        dir: &Path,
        maker: Arc<dyn EnvMaker>,
    ) -> Result<(), RunError> {
        // The same family again, as the set-up found it (a suite from the run's copy, else the
        // named file), to wrap (the set-up's is boxed in place).
        let copy = RunDir::at(dir).suite_path();
        let inner = pdt_envs::family_of_run(&self.cfg.env.name, &copy)?;
        self.family = Box::new(MadeBy { inner, maker });
        self.caller_envs = true;
        Ok(())
    }
}

/// The run's family with its batches of environments made by a caller's [`EnvMaker`]; all else
/// (tasks, splits, constants) is the family's. The evaluations make their environments only
/// through `make_batch`; a single environment (`make`: rendering, replay) stays the family's.
/// Every method of [`EnvFamily`] is forwarded, so a method added to the trait with a default
/// must be forwarded here too.
struct MadeBy {
    inner: Box<dyn EnvFamily>,
    maker: Arc<dyn EnvMaker>,
}

impl EnvFamily for MadeBy {
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn num_tasks(&self) -> usize {
        self.inner.num_tasks()
    }
    fn preset(&self) -> EnvPreset {
        self.inner.preset()
    }
    fn split_names(&self) -> Vec<String> {
        self.inner.split_names()
    }
    fn split(&self, name: &str) -> Result<(Vec<usize>, Vec<usize>), EnvError> {
        self.inner.split(name)
    }
    fn task_params(&self, task: usize) -> Result<serde_json::Value, EnvError> {
        self.inner.task_params(task)
    }
    fn make(&self, task: usize) -> Result<Box<dyn Env>, EnvError> {
        self.inner.make(task)
    }
    fn make_batch(&self, tasks: &[usize], _threads: usize) -> Result<VecEnv, EnvError> {
        self.maker.make_batch(self.inner.as_ref(), tasks)
    }
    fn render_fps(&self) -> u32 {
        self.inner.render_fps()
    }
    fn action_bounds(&self) -> ActionBounds {
        self.inner.action_bounds()
    }
    fn success_reward(&self) -> Option<f32> {
        self.inner.success_reward()
    }
    // The rest forwarded too, though no evaluation asks: the family stays the family in all but
    // where its environments are made.
    fn scripted(&self) -> Option<pdt_envs::collect_scripted::ScriptedFamily> {
        self.inner.scripted()
    }
    fn rl_preset(&self) -> Option<&'static str> {
        self.inner.rl_preset()
    }
    fn task_features(&self, task: usize) -> Result<Vec<f32>, EnvError> {
        self.inner.task_features(task)
    }
    fn symmetries(&self) -> Vec<pdt_envs::BodySymmetry> {
        self.inner.symmetries()
    }
    fn dataset_bar(&self) -> Option<pdt_envs::DatasetBar> {
        self.inner.dataset_bar()
    }
    fn replay(
        &self,
        task: usize,
        init: Option<&str>,
        actions: &[Vec<f32>],
    ) -> Result<pdt_envs::ReplayResult, EnvError> {
        self.inner.replay(task, init, actions)
    }
    fn task_target_return(&self, task: usize) -> Option<f32> {
        self.inner.task_target_return(task)
    }
    fn reference_returns(&self, task: usize) -> Option<(f64, f64)> {
        self.inner.reference_returns(task)
    }
    fn as_suite(&self) -> Option<&pdt_envs::suite::SuiteFamily> {
        self.inner.as_suite()
    }
}
