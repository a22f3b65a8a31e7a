//! A training run: data and environments set up from a [`TrainConfig`], the reference's loop
//! (iterations of gradient steps, periodic evaluation of test and train tasks), checkpoints written
//! atomically, and exact resumption. The run directory layout is `docs/run-directory.md`.
//!
//! Randomness: one seed, split into independent streams (model init, batch sampling, dropout per
//! iteration, evaluation per iteration), so a resumed run draws exactly what an uninterrupted one
//! would, and evaluation never disturbs training.

use crate::config::{
    compact, ConfigError, Method, MtBcEval, TrainConfig, MAX_RETURN_TOKEN, MAX_STATE_STAT,
};
use crate::optim::{AdamW, AdamWConfig, ParamState};
use crate::step::{train_step, DeviceBatch, LossOn, StepStats};
use pdt_data::multitask::{load_multitask, DatasetSpec};
use pdt_data::{DataError, MultiTaskDataset, TaskData};
use pdt_envs::{EnvError, EnvFamily, EnvPreset};
use pdt_eval::{
    evaluate, summarise, EvalError, EvalReturns, EvalSettings, EvalTask, TaskResult, ToModelConfig,
};
use pdt_model::checkpoint::{self, write_atomic, CheckpointError};
use pdt_model::{PromptDt, PromptDtConfig};
use pdt_prompt::{
    BatchSampler, NormalizationScope, Rng, SamplerConfig, SamplerError, SegmentBatch, StateNorm,
};
use rand::{RngCore, SeedableRng};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use tch::{nn::VarStore, Device, Tensor};

#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Data(#[from] DataError),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Sampler(#[from] SamplerError),
    #[error(transparent)]
    Eval(#[from] EvalError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(transparent)]
    Device(#[from] pdt_model::device::DeviceError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {message}")]
    Corrupt { path: PathBuf, message: String },
    #[error("{0}")]
    Invalid(String),
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RunError + '_ {
    move |source| RunError::Io { path: path.into(), source }
}

// Independent random streams derived from the run seed (SplitMix64 of seed, stream, counter).
use pdt_base::seed::derive_seed;
pub(crate) const STREAM_INIT: u64 = 1;
pub(crate) const STREAM_BATCHES: u64 = 2;
const STREAM_DROPOUT: u64 = 3;
pub(crate) const STREAM_EVAL_TEST: u64 = 4;
pub(crate) const STREAM_EVAL_TRAIN: u64 = 5;

/// Which tasks an evaluation covers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Split {
    Test,
    Train,
}

/// The run's identity (`run.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunInfo {
    pub name: String,
    pub method: String,
    pub env: String,
    pub seed: u64,
    pub split: String,
    pub created: String,
    pub promptdt_version: String,
}

/// What evaluation needs besides weights (`task_stats.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskStats {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub state_mean: Vec<f32>,
    pub state_std: Vec<f32>,
    pub rtg_scale: f32,
    pub target_return: f32,
    pub horizon: usize,
    pub train_tasks: Vec<usize>,
    pub test_tasks: Vec<usize>,
    /// Content hashes of the training and test data (`MultiTaskDataset::fingerprint`): a resumed
    /// or evaluated run refuses data that differs. Empty in runs made before they were recorded.
    #[serde(default)]
    pub train_data_fingerprint: String,
    #[serde(default)]
    pub test_data_fingerprint: String,
}

impl TaskStats {
    /// The values a policy can act with: one mean and std per state dimension, finite, each std
    /// positive, all within [`MAX_STATE_STAT`]; a positive finite rtg scale; a finite target.
    pub fn check(&self) -> Result<(), String> {
        let n = self.obs_dim;
        if self.state_mean.len() != n || self.state_std.len() != n {
            return Err(format!(
                "state_mean has {} values and state_std {}, but obs_dim is {n}",
                self.state_mean.len(),
                self.state_std.len()
            ));
        }
        for (j, (&m, &s)) in self.state_mean.iter().zip(&self.state_std).enumerate() {
            let ok = within(f64::from(m), MAX_STATE_STAT)
                && s > 0.0
                && within(f64::from(s), MAX_STATE_STAT);
            if !ok {
                return Err(format!(
                    "state_mean[{j}] = {}, state_std[{j}] = {}: each must be finite and within {} \
                     in magnitude, the std positive",
                    compact(m),
                    compact(s),
                    compact(MAX_STATE_STAT)
                ));
            }
        }
        let ok =
            self.rtg_scale > 0.0 && self.rtg_scale.is_finite() && self.target_return.is_finite();
        if !ok {
            return Err(format!(
                "rtg_scale = {} must be positive and finite, target_return = {} finite",
                compact(self.rtg_scale),
                compact(self.target_return)
            ));
        }
        Ok(())
    }

    /// Compares the statistics recomputed from the data now with those recorded in a run;
    /// `Err` says what differs. Fingerprints are compared when the run recorded them.
    fn check_same_as(&self, recorded: &TaskStats) -> Result<(), String> {
        let fp = |now: &str, then: &str, which: &str| {
            if !then.is_empty() && now != then {
                Err(format!(
                    "the {which} data differ from what the run trained on ({then}, now {now})"
                ))
            } else {
                Ok(())
            }
        };
        fp(&self.train_data_fingerprint, &recorded.train_data_fingerprint, "training")?;
        fp(&self.test_data_fingerprint, &recorded.test_data_fingerprint, "test")?;
        let mut mine = self.clone();
        mine.train_data_fingerprint.clone_from(&recorded.train_data_fingerprint);
        mine.test_data_fingerprint.clone_from(&recorded.test_data_fingerprint);
        if &mine != recorded {
            return Err("the state statistics, tasks or return settings recomputed from the \
                        configuration and data differ from those the run recorded"
                .into());
        }
        Ok(())
    }
}

/// The commit point of a checkpoint (`checkpoints/latest.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Latest {
    pub(crate) step: u64,
    pub(crate) iteration: u64,
    pub(crate) model: String,
    pub(crate) state: String,
    /// `false` for a resume point between checkpoints (`train.resume_interval`): its weights are
    /// removed once a later checkpoint is in force. Absent in runs written before the option.
    #[serde(default = "keep_default")]
    pub(crate) keep: bool,
}

fn keep_default() -> bool {
    true
}

/// Training state besides weights and moments (`checkpoints/state_<N>.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct TrainState {
    iteration: u64,
    step: u64,
    /// Position of the batch-sampling RNG (a u128, as a decimal string).
    batch_rng_word_pos: String,
    adam_steps: BTreeMap<String, u64>,
    metrics_lines: usize,
    eval_lines: usize,
    /// As `latest.json`'s `keep`: `false` for a resume point, whose files go once a later one is
    /// in force. Recorded here too, so a removal cut short by a kill is finished on the next start
    /// (`remove_orphans`). Absent in runs written before it was recorded (then kept).
    #[serde(default = "keep_default")]
    keep: bool,
}

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
}

/// What may change when a run is resumed. Anything else (seed, method, data settings) would make
/// it another run; the CLI refuses those flags with `--resume`.
#[derive(Debug, Clone, Default)]
pub struct ResumeWith {
    /// Extend `train.iterations` (at least the iterations already done); written to `config.toml`.
    pub iterations: Option<u64>,
    /// Run on this device this time (the results of a CPU and a GPU run differ in rounding only).
    pub device: Option<pdt_model::device::DeviceSpec>,
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
}

/// Everything built from the configuration and the data.
pub(crate) struct Setup {
    pub(crate) cfg: TrainConfig,
    pub(crate) family: Box<dyn EnvFamily>,
    pub(crate) preset: EnvPreset,
    pub(crate) train_data: MultiTaskDataset,
    pub(crate) test_data: MultiTaskDataset,
    norm: StateNorm,
    pub(crate) sampler_cfg: SamplerConfig,
    model_cfg: PromptDtConfig,
    pub(crate) device: Device,
    pub(crate) stats: TaskStats,
}

impl Setup {
    fn new(cfg: TrainConfig) -> Result<Self, RunError> {
        cfg.validate()?;
        let family = pdt_envs::family(&cfg.env.name)?;
        let preset = family.preset();
        let (train_tasks, test_tasks) = family.split(&cfg.env.split)?;
        let env_name = family.name().to_string();
        let spec = |tasks: &[usize], d: &str, p: &str| DatasetSpec {
            dir: cfg.data.dir.clone(),
            env: env_name.clone(),
            tasks: tasks.to_vec(),
            dataset_mode: d.to_string(),
            prompt_mode: p.to_string(),
            format: cfg.data.format,
        };
        let train_data =
            load_multitask(&spec(&train_tasks, &cfg.data.dataset_mode, &cfg.data.prompt_mode))?;
        let test_data = load_multitask(&spec(
            &test_tasks,
            &cfg.data.test_dataset_mode,
            &cfg.data.test_prompt_mode,
        ))?;
        let (ds, da) = (train_data.obs_dim, train_data.act_dim);
        if (ds, da) != (preset.obs_dim, preset.act_dim)
            || (test_data.obs_dim, test_data.act_dim) != (ds, da)
        {
            return Err(RunError::Invalid(format!(
                "data in {} has obs/act dims {ds}/{da} (test {}/{}), but {} has {}/{}",
                cfg.data.dir.display(),
                test_data.obs_dim,
                test_data.act_dim,
                env_name,
                preset.obs_dim,
                preset.act_dim
            )));
        }
        let train_ds = train_data.tasks.iter().map(|t| &t.dataset);
        // Reference quirk (pitfall 4): the statistics include the test tasks' datasets.
        let norm = match cfg.data.normalization {
            NormalizationScope::TrainAndTest => StateNorm::from_datasets(
                ds,
                train_ds.chain(test_data.tasks.iter().map(|t| &t.dataset)),
            ),
            NormalizationScope::TrainOnly => StateNorm::from_datasets(ds, train_ds),
            NormalizationScope::None => StateNorm::identity(ds),
        };
        let s = &cfg.sampler;
        let sampler_cfg = SamplerConfig {
            k: s.k,
            prompt_episodes: s.prompt_episodes,
            prompt_length: s.prompt_length.unwrap_or(preset.prompt_length),
            prompt_position: s.prompt_position,
            batch_size_per_task: s.batch_size_per_task,
            rtg_scale: s.rtg_scale.unwrap_or(preset.rtg_scale),
            max_ep_len: preset.horizon,
            ranking: s.ranking,
            zero_history_returns: cfg.run.method.zeroes_history_returns(),
        };
        if cfg.run.method != Method::Macaw {
            check_return_tokens(&cfg, &preset, &env_name, &train_data, &test_data)?;
        }
        if cfg.data.normalization != NormalizationScope::None {
            check_state_stats(&cfg, &env_name, &norm, &train_data, &test_data)?;
        }
        // Timesteps index the embedding table: an episode longer than it would index past it.
        let longest = train_data
            .tasks
            .iter()
            .chain(&test_data.tasks)
            .flat_map(|t| t.dataset.trajectories.iter().chain(&t.prompts.trajectories))
            .map(|t| t.len())
            .max()
            .unwrap_or(0)
            .max(preset.horizon);
        if cfg.model.max_ep_len < longest {
            return Err(RunError::Invalid(format!(
                "model.max_ep_len = {} is below the longest episode ({longest} steps: {}'s \
                 horizon or its data); timesteps would index past the embedding table",
                cfg.model.max_ep_len, env_name
            )));
        }
        let model_cfg = cfg.model.to_model_config(ds, da);
        model_cfg.validate().map_err(RunError::Invalid)?;
        sampler_cfg.validate(model_cfg.n_positions)?;
        let device = pdt_model::device::resolve(cfg.run.device)?;
        let stats = TaskStats {
            obs_dim: ds,
            act_dim: da,
            state_mean: norm.mean.clone(),
            state_std: norm.std.clone(),
            rtg_scale: sampler_cfg.rtg_scale,
            target_return: cfg.eval.target_return.unwrap_or(preset.target_return),
            horizon: preset.horizon,
            train_tasks,
            test_tasks,
            train_data_fingerprint: train_data.fingerprint(),
            test_data_fingerprint: test_data.fingerprint(),
        };
        Ok(Self {
            cfg,
            family,
            preset,
            train_data,
            test_data,
            norm,
            sampler_cfg,
            model_cfg,
            device,
            stats,
        })
    }

    fn sampler<'a>(&self, data: &'a MultiTaskDataset) -> Result<BatchSampler<'a>, RunError> {
        let tasks: Vec<&TaskData> = data.tasks.iter().collect();
        Ok(BatchSampler::new(
            self.sampler_cfg.clone(),
            &tasks,
            self.norm.clone(),
            self.model_cfg.n_positions,
        )?)
    }

    fn eval_returns(&self) -> EvalReturns {
        eval_returns(&self.cfg)
    }
}

/// How a setting with a preset default is named in messages: `sampler.rtg_scale = 1e-30` when set,
/// `the rtg scale 10 (point_robot's preset; sampler.rtg_scale)` when not.
fn setting(name: &str, what: &str, set: Option<f32>, preset: f32, env: &str) -> String {
    match set {
        Some(x) => format!("{name} = {}", compact(x)),
        None => format!("the {what} {} ({env}'s preset; {name})", compact(preset)),
    }
}

/// A value computed in f64 from f32 settings, printed as the f32 it is close to (`1e29`, not
/// `1.0000000150474662e29`) when it is one.
fn shown(x: f64) -> String {
    let y = x as f32;
    if y.is_finite() {
        compact(y)
    } else {
        compact(x)
    }
}

/// The file of task `t`'s data of kind `mode` (`expert`, `prompt-expert`), for messages; the task
/// and mode when it cannot be found again.
fn task_file(cfg: &TrainConfig, env: &str, t: &TaskData, mode: &str) -> String {
    pdt_data::multitask::resolve_task_file(&cfg.data.dir, env, t.id.index, mode, cfg.data.format)
        .map_or_else(|_| format!("task {}'s {mode} data", t.id), |p| p.display().to_string())
}

/// `|x| <= bound`, false for NaN.
fn within(x: f64, bound: f64) -> bool {
    x.abs() <= bound
}

/// Refuses return-to-go tokens the model cannot represent: the target return's (the first token of
/// every evaluation episode) and the data's (training and prompt tokens), each over the rtg scale,
/// must stay within [`MAX_RETURN_TOKEN`] in magnitude.
fn check_return_tokens(
    cfg: &TrainConfig,
    preset: &EnvPreset,
    env: &str,
    train: &MultiTaskDataset,
    test: &MultiTaskDataset,
) -> Result<(), RunError> {
    let scale = cfg.sampler.rtg_scale.unwrap_or(preset.rtg_scale);
    let scale_name = setting("sampler.rtg_scale", "rtg scale", cfg.sampler.rtg_scale, scale, env);
    let target = cfg.eval.target_return.unwrap_or(preset.target_return);
    let token = f64::from(target) / f64::from(scale);
    if !within(token, MAX_RETURN_TOKEN) {
        let target_name =
            setting("eval.target_return", "target return", cfg.eval.target_return, target, env);
        return Err(RunError::Invalid(format!(
            "{target_name} over {scale_name} gives the return token {}, beyond {} in magnitude: \
             the model cannot represent it (its return embedding overflows f32 and the actions \
             come out NaN). Lower eval.target_return or raise sampler.rtg_scale",
            shown(token),
            compact(MAX_RETURN_TOKEN)
        )));
    }
    // The largest return-to-go of the data (from any step, D_i and P_i alike), and where it is.
    let d = &cfg.data;
    let mut worst: Option<(f64, &TaskData, String, usize, usize)> = None;
    for (set, modes) in [
        (train, (&d.dataset_mode, &d.prompt_mode)),
        (test, (&d.test_dataset_mode, &d.test_prompt_mode)),
    ] {
        for t in &set.tasks {
            for (trajs, mode) in
                [(&t.dataset, modes.0.clone()), (&t.prompts, format!("prompt-{}", modes.1))]
            {
                for (k, tr) in trajs.trajectories.iter().enumerate() {
                    let mut rtg = 0f64;
                    for (step, r) in tr.rewards.iter().enumerate().rev() {
                        rtg += f64::from(*r);
                        if worst.as_ref().is_none_or(|w| rtg.abs() > w.0.abs()) {
                            worst = Some((rtg, t, mode.clone(), k, step));
                        }
                    }
                }
            }
        }
    }
    if let Some((rtg, t, mode, k, step)) = worst {
        let token = rtg / f64::from(scale);
        if !within(token, MAX_RETURN_TOKEN) {
            return Err(RunError::Invalid(format!(
                "the return-to-go {} of {} (trajectory {k}, from step {step}) over {scale_name} \
                 gives the return token {}, beyond {} in magnitude: the model cannot represent \
                 it. Raise sampler.rtg_scale",
                shown(rtg),
                task_file(cfg, env, t, &mode),
                shown(token),
                compact(MAX_RETURN_TOKEN)
            )));
        }
    }
    Ok(())
}

/// Refuses state statistics that are not finite or absurd (beyond [`MAX_STATE_STAT`]), naming the
/// dimension and the file holding the observation that made them so. A non-finite statistic
/// could not even be recorded (`task_stats.json` would hold `null`).
fn check_state_stats(
    cfg: &TrainConfig,
    env: &str,
    norm: &StateNorm,
    train: &MultiTaskDataset,
    test: &MultiTaskDataset,
) -> Result<(), RunError> {
    let bad = |x: f32| !within(f64::from(x), MAX_STATE_STAT);
    let Some(j) = (0..norm.mean.len()).find(|&j| bad(norm.mean[j]) || bad(norm.std[j])) else {
        return Ok(());
    };
    // The datasets the statistics were computed over (`StateNorm::from_datasets` in `Setup::new`).
    let mut sets: Vec<(&TaskData, &str)> =
        train.tasks.iter().map(|t| (t, cfg.data.dataset_mode.as_str())).collect();
    if cfg.data.normalization == NormalizationScope::TrainAndTest {
        sets.extend(test.tasks.iter().map(|t| (t, cfg.data.test_dataset_mode.as_str())));
    }
    let od = norm.mean.len();
    let mut worst: Option<(f32, &TaskData, &str, usize, usize)> = None;
    for &(t, mode) in &sets {
        for (k, tr) in t.dataset.trajectories.iter().enumerate() {
            for (step, row) in tr.observations.chunks_exact(od).enumerate() {
                if worst.as_ref().is_none_or(|w| row[j].abs() > w.0.abs()) {
                    worst = Some((row[j], t, mode, k, step));
                }
            }
        }
    }
    let at = match worst {
        Some((x, t, mode, k, step)) => {
            let file = task_file(cfg, env, t, mode);
            format!(
                "; the largest magnitude there is observations[{j}] = {} in {file} (trajectory \
                 {k}, step {step})",
                compact(x)
            )
        }
        None => String::new(),
    };
    Err(RunError::Invalid(format!(
        "the state statistics (data.normalization = {}) have state_mean[{j}] = {} and \
         state_std[{j}] = {}: each must be finite and within {} in magnitude{at}. Normalising by \
         them would map every ordinary state to about 0 (or NaN); fix the data",
        serde_json::to_string(&cfg.data.normalization).unwrap_or_default(),
        compact(norm.mean[j]),
        compact(norm.std[j]),
        compact(MAX_STATE_STAT)
    )))
}

/// The return tokens an acting policy feeds (Prompt-MT-BC and MT-BC-Finetune: constant or zero).
fn eval_returns(cfg: &TrainConfig) -> EvalReturns {
    match (cfg.run.method.zeroes_history_returns(), cfg.eval.mt_bc_returns) {
        (false, _) => EvalReturns::Decreasing,
        (true, MtBcEval::Reference) => EvalReturns::Constant,
        (true, MtBcEval::Paper) => EvalReturns::Zero,
    }
}

/// Model and optimiser of a run.
struct Learner {
    vs: VarStore,
    model: PromptDt,
    opt: AdamW,
}

impl Learner {
    fn new(setup: &Setup) -> Self {
        tch::manual_seed(derive_seed(setup.cfg.run.seed, STREAM_INIT, 0) as i64);
        let vs = VarStore::new(setup.device);
        let model = PromptDt::new(&vs.root(), &setup.model_cfg);
        let opt = AdamW::new(&vs, &setup.model_cfg.parameter_names(), setup.cfg.optim.clone());
        Self { vs, model, opt }
    }
}

/// What an evaluation draws for one task: the prompt its episodes share and their reset seeds.
#[derive(Debug, Clone)]
pub struct TaskPlan {
    /// `cheetah_vel-2`
    pub name: String,
    /// Task index in its family.
    pub index: usize,
    /// `None` for the methods without a prompt.
    pub prompt: Option<SegmentBatch>,
    /// Reset seed of each episode.
    pub seeds: Vec<u64>,
}

/// Draws task `i`'s prompt (once per task and evaluation call, shared by its episodes, as the
/// reference does), then its episodes' seeds, from `rng`.
fn plan_task(
    setup: &Setup,
    sampler: &BatchSampler,
    data: &MultiTaskDataset,
    i: usize,
    episodes: usize,
    rng: &mut Rng,
) -> TaskPlan {
    let t = &data.tasks[i];
    let prompt = sampler.eval_prompt(i, rng);
    let seeds = (0..episodes).map(|_| rng.next_u64()).collect();
    TaskPlan {
        name: t.id.to_string(),
        index: t.id.index,
        prompt: setup.cfg.run.method.uses_prompt().then_some(prompt),
        seeds,
    }
}

/// Evaluates `tasks` (indices into `data`), each with its own prompt, all episodes together.
fn eval_tasks(
    setup: &Setup,
    learner: &mut Learner,
    split: Split,
    iteration: u64,
) -> Result<Vec<TaskResult>, RunError> {
    let (data, stream) = match split {
        Split::Test => (&setup.test_data, STREAM_EVAL_TEST),
        Split::Train => (&setup.train_data, STREAM_EVAL_TRAIN),
    };
    let sampler = setup.sampler(data)?;
    let mut rng = Rng::seed_from_u64(derive_seed(setup.cfg.run.seed, stream, iteration));
    let method = setup.cfg.run.method;
    let make = |i: usize, rng: &mut Rng| -> Result<EvalTask, RunError> {
        let plan = plan_task(setup, &sampler, data, i, setup.cfg.eval.episodes, rng);
        let envs = (0..plan.seeds.len())
            .map(|_| setup.family.make(plan.index))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(EvalTask {
            name: plan.name,
            index: plan.index,
            envs,
            seeds: plan.seeds,
            prompt: plan.prompt,
        })
    };
    let settings = EvalSettings {
        k: setup.sampler_cfg.k,
        horizon: setup.preset.horizon,
        rtg_scale: setup.sampler_cfg.rtg_scale,
        target_return: setup.stats.target_return,
        returns: setup.eval_returns(),
        norm: setup.norm.clone(),
        max_batch: setup.cfg.eval.max_batch,
        device: setup.device,
        env_threads: match setup.cfg.eval.env_threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n,
        },
        inference: setup.cfg.eval.inference,
    };
    // `positions[k]` is the task (index into `data.tasks`) of the k-th task passed to `evaluate`,
    // whose episodes carry `task_index == k`.
    let summarise_all = |positions: &[usize], eps: &[pdt_eval::EpisodeRecord]| -> Vec<TaskResult> {
        positions
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                let id = &data.tasks[i].id;
                let mine: Vec<_> = eps.iter().filter(|e| e.task_index == k).collect();
                summarise(&id.to_string(), id.index, &mine)
            })
            .collect()
    };
    // The reference fine-tunes before test-task evaluations only; training tasks are evaluated as is.
    if method != Method::MtBcFinetune || split == Split::Train {
        let tasks =
            (0..data.tasks.len()).map(|i| make(i, &mut rng)).collect::<Result<Vec<_>, _>>()?;
        let eps = evaluate(&learner.model, tasks, &settings)?;
        let positions: Vec<usize> = (0..data.tasks.len()).collect();
        return Ok(summarise_all(&positions, &eps));
    }
    // MT-BC-Finetune: per task, adapt a copy of the weights on the task's demonstrations with a
    // fresh optimiser, evaluate, restore. (The reference shares one optimiser across the test tasks
    // of an evaluation, leaking Adam moments between them: pitfall 13, fixed here.)
    let snapshot: Vec<(String, Tensor)> =
        learner.vs.variables().into_iter().map(|(n, t)| (n, t.copy())).collect();
    let mut results = Vec::new();
    for i in 0..data.tasks.len() {
        let task = make(i, &mut rng)?;
        let ocfg = AdamWConfig {
            learning_rate: setup.cfg.eval.finetune_lr,
            warmup_steps: 1,
            ..setup.cfg.optim.clone()
        };
        let mut opt = AdamW::new(&learner.vs, &setup.model_cfg.parameter_names(), ocfg);
        for s in 0..setup.cfg.eval.finetune_steps {
            let seg = sampler.tail_segments(
                i,
                setup.cfg.eval.finetune_batch,
                setup.sampler_cfg.prompt_length,
                &mut rng,
            );
            let history = crate::step::to_segments(&seg, setup.device);
            train_step(
                &learner.model,
                &mut opt,
                &DeviceBatch { history, prompt: None },
                LossOn::History,
                s,
            );
        }
        let eps = evaluate(&learner.model, vec![task], &settings)?;
        results.extend(summarise_all(&[i], &eps));
        tch::no_grad(|| {
            let vars = learner.vs.variables();
            for (n, saved) in &snapshot {
                if let Some(v) = vars.get(n) {
                    v.shallow_clone().copy_(saved);
                }
            }
        });
    }
    Ok(results)
}

/// Appends JSON lines (and matching CSV rows) to a log.
pub(crate) struct Log {
    jsonl: PathBuf,
    csv: PathBuf,
    pub(crate) lines: usize,
    /// `time/elapsed_s` of the last kept line (0 for a new log). A resumed run adds its own time to
    /// it, so the column is the training time of the kept iterations, not the time since the last
    /// resume (the time between the last resume point and a kill is not counted: that work is redone).
    pub(crate) elapsed_before: f64,
}

impl Log {
    pub(crate) fn open(dir: &Path, stem: &str, keep_lines: usize) -> Result<Self, RunError> {
        let (jsonl, csv) = (dir.join(format!("{stem}.jsonl")), dir.join(format!("{stem}.csv")));
        // Keep exactly the lines the checkpoint knew about: a killed run may have written more.
        // The JSON lines are the record; the CSV is rebuilt from them (a deleted or edited CSV
        // is repaired, with its header).
        let text = match std::fs::read_to_string(&jsonl) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
            Err(e) => return Err(RunError::Io { path: jsonl, source: e }),
        };
        let kept: Vec<&str> = text.lines().take(keep_lines).collect();
        if kept.len() < keep_lines {
            return Err(RunError::Corrupt {
                path: jsonl,
                message: format!(
                    "{} lines, but the checkpoint recorded {keep_lines}: the log was truncated or \
                     deleted. Restore it, or start the run again",
                    kept.len()
                ),
            });
        }
        let mut log =
            Self { jsonl: jsonl.clone(), csv: csv.clone(), lines: 0, elapsed_before: 0.0 };
        let mut rows = Vec::with_capacity(kept.len());
        for (i, line) in kept.iter().enumerate() {
            match serde_json::from_str::<serde_json::Value>(line) {
                Ok(serde_json::Value::Object(m)) => rows.push(m),
                _ => {
                    return Err(RunError::Corrupt {
                        path: jsonl,
                        message: format!("line {} is not a JSON object", i + 1),
                    })
                }
            }
        }
        let (j, c) = log.render(&rows);
        write_atomic(&jsonl, j.as_bytes()).map_err(io_err(&jsonl))?;
        write_atomic(&csv, c.as_bytes()).map_err(io_err(&csv))?;
        log.lines = rows.len();
        log.elapsed_before = rows
            .last()
            .and_then(|r| r.get("time/elapsed_s"))
            .and_then(serde_json::Value::as_f64)
            .unwrap_or(0.0);
        Ok(log)
    }

    /// The JSON lines and CSV rows (with the header when the log is empty) of `rows`.
    fn render(&self, rows: &[serde_json::Map<String, serde_json::Value>]) -> (String, String) {
        let (mut j, mut c) = (String::new(), String::new());
        for (i, row) in rows.iter().enumerate() {
            if self.lines + i == 0 {
                let header: Vec<&str> = row.keys().map(String::as_str).collect();
                c.push_str(&header.join(","));
                c.push('\n');
            }
            let values: Vec<String> = row
                .values()
                .map(|v| v.as_str().map_or_else(|| v.to_string(), str::to_string))
                .collect();
            c.push_str(&values.join(","));
            c.push('\n');
            j.push_str(&serde_json::Value::Object(row.clone()).to_string());
            j.push('\n');
        }
        (j, c)
    }

    pub(crate) fn append(
        &mut self,
        rows: &[serde_json::Map<String, serde_json::Value>],
    ) -> Result<(), RunError> {
        let mut j = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.jsonl)
            .map_err(io_err(&self.jsonl))?;
        let mut c = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.csv)
            .map_err(io_err(&self.csv))?;
        let (text_j, text_c) = self.render(rows);
        c.write_all(text_c.as_bytes()).map_err(io_err(&self.csv))?;
        j.write_all(text_j.as_bytes()).map_err(io_err(&self.jsonl))?;
        self.lines += rows.len();
        Ok(())
    }
}

pub(crate) fn eval_rows(
    results: &[TaskResult],
    iteration: u64,
    step: u64,
    split: &str,
    target: f32,
) -> Vec<serde_json::Map<String, serde_json::Value>> {
    results
        .iter()
        .map(|r| {
            let v = serde_json::json!({
                "iteration": iteration, "step": step, "split": split, "task": r.task, "task_index": r.task_index,
                "return_mean": r.return_mean, "return_std": r.return_std, "length_mean": r.length_mean,
                "episodes": r.episodes, "target_return": target,
            });
            let mut row = v.as_object().cloned().unwrap_or_default();
            // Only families with a success criterion (Meta-World) have the column.
            if let Some(rate) = r.success_rate {
                row.insert("success_rate".into(), rate.into());
            }
            row
        })
        .collect()
}

pub(crate) fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), RunError> {
    let text = serde_json::to_string_pretty(value)
        .map_err(|e| RunError::Corrupt { path: path.into(), message: e.to_string() })?;
    write_atomic(path, text.as_bytes()).map_err(io_err(path))
}

pub(crate) fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, RunError> {
    let text = pdt_base::fs::read_text_limited(path, pdt_base::fs::MAX_TEXT_BYTES)
        .map_err(io_err(path))?;
    serde_json::from_str(&text)
        .map_err(|e| RunError::Corrupt { path: path.into(), message: e.to_string() })
}

/// Saves weights, optimiser state and the training state; `latest.json` is written last, so a
/// crash before it leaves the previous checkpoint in force.
fn save_checkpoint(
    dir: &Path,
    learner: &Learner,
    state: &TrainState,
    keep: bool,
) -> Result<(), RunError> {
    let ck = dir.join("checkpoints");
    std::fs::create_dir_all(&ck).map_err(io_err(&ck))?;
    let (model, opt_state) =
        (format!("step_{}.safetensors", state.step), format!("state_{}.safetensors", state.step));
    checkpoint::save(&learner.vs, &ck.join(&model), &learner.model.cfg)?;
    let mut named: Vec<(String, Tensor)> = Vec::new();
    for (name, st) in &learner.opt.state {
        named.push((format!("exp_avg.{name}"), st.exp_avg.to_device(Device::Cpu)));
        named.push((format!("exp_avg_sq.{name}"), st.exp_avg_sq.to_device(Device::Cpu)));
    }
    let tmp = ck.join(temp_name(&opt_state));
    Tensor::write_safetensors(&named, &tmp)
        .map_err(|e| RunError::Corrupt { path: tmp.clone(), message: e.to_string() })?;
    std::fs::rename(&tmp, ck.join(&opt_state)).map_err(io_err(&tmp))?;
    write_json(&ck.join(format!("state_{}.json", state.step)), state)?;
    commit_checkpoint(
        &ck,
        Latest { step: state.step, iteration: state.iteration, model, state: opt_state, keep },
    )
}

/// Makes a checkpoint whose files are written the one in force: `latest.json` last, so a crash
/// before it leaves the previous one in force; then what the previous one no longer needs goes.
pub(crate) fn commit_checkpoint(ck: &Path, latest: Latest) -> Result<(), RunError> {
    let previous: Option<Latest> = read_json(&ck.join("latest.json")).ok();
    let step = latest.step;
    write_json(&ck.join("latest.json"), &latest)?;
    // Optimiser moments are only needed to resume: keep the latest ones. Weights are kept at
    // every checkpoint; a resume point's go once a later one is in force.
    if let Some(p) = previous.filter(|p| p.step != step) {
        let _ = std::fs::remove_file(ck.join(&p.state));
        if !p.keep {
            let _ = std::fs::remove_file(ck.join(&p.model));
            let _ = std::fs::remove_file(ck.join(format!("state_{}.json", p.step)));
        }
    }
    Ok(())
}

fn load_checkpoint(
    dir: &Path,
    setup: &Setup,
    learner: &mut Learner,
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
    let (model, opt) =
        (format!("step_{}.safetensors", latest.step), format!("state_{}.safetensors", latest.step));
    if latest.model != model || latest.state != opt {
        return Err(corrupt(
            &latest_path,
            format!(
                "names `{}` and `{}` for step {}; expected `{model}` and `{opt}`",
                latest.model, latest.state, latest.step
            ),
        ));
    }
    let state_path = ck.join(format!("state_{}.json", latest.step));
    let state: TrainState = read_json(&state_path)?;
    let per = setup.cfg.train.steps_per_iteration;
    if state.step != latest.step
        || state.iteration != latest.iteration
        || state.step != state.iteration.saturating_mul(per)
    {
        return Err(corrupt(
            &state_path,
            format!(
                "iteration {} step {}, but latest.json says iteration {} step {} (and \
                 train.steps_per_iteration = {per})",
                state.iteration, state.step, latest.iteration, latest.step
            ),
        ));
    }
    check_log_counts(&state_path, state.iteration, state.metrics_lines, state.eval_lines, setup)?;
    if let Some((name, n)) = state.adam_steps.iter().find(|(_, &n)| n != state.step) {
        return Err(corrupt(
            &state_path,
            format!("optimiser step {n} for `{name}` at step {}", state.step),
        ));
    }
    checkpoint::load(&mut learner.vs, &ck.join(&latest.model), learner.model.cfg.n_layer)?;
    let opt_path = ck.join(&latest.state);
    let tensors: BTreeMap<String, Tensor> = Tensor::read_safetensors(&opt_path)
        .map_err(|e| RunError::Corrupt { path: opt_path.clone(), message: e.to_string() })?
        .into_iter()
        .collect();
    let device = learner.vs.device();
    for (name, &step) in &state.adam_steps {
        let get = |k: String| {
            tensors.get(&k).map(|t| t.to_device(device)).ok_or_else(|| RunError::Corrupt {
                path: opt_path.clone(),
                message: format!("missing `{k}`"),
            })
        };
        let st = ParamState {
            step,
            exp_avg: get(format!("exp_avg.{name}"))?,
            exp_avg_sq: get(format!("exp_avg_sq.{name}"))?,
        };
        learner.opt.state.insert(name.clone(), st);
    }
    Ok(Some(state))
}

/// A state file's log line counts against what its iteration implies: one metrics line per
/// iteration, and at least one evaluation line per task for each scheduled evaluation (after
/// iteration 1 and every interval after it; the last iteration of each earlier call adds more, so
/// this is a lower bound). A smaller count would truncate the logs on resume: refused, naming both.
pub(crate) fn check_log_counts(
    state_path: &Path,
    iteration: u64,
    metrics_lines: usize,
    eval_lines: usize,
    setup: &Setup,
) -> Result<(), RunError> {
    let (test_tasks, train_tasks) = (setup.test_data.tasks.len(), setup.train_data.tasks.len());
    let corrupt = |message: String| RunError::Corrupt { path: state_path.into(), message };
    if metrics_lines as u64 != iteration {
        return Err(corrupt(format!(
            "metrics_lines = {metrics_lines}, but iteration {iteration} implies {iteration} (one \
             metrics line per iteration); the state file was edited or is corrupt, and resuming \
             would cut metrics.jsonl to its count. Nothing was changed"
        )));
    }
    // Evaluations after iterations 1, 1 + n, ... up to `iteration`.
    let scheduled = |n: u64| if iteration == 0 || n == 0 { 0 } else { (iteration - 1) / n + 1 };
    let t = &setup.cfg.train;
    let least = scheduled(t.test_eval_interval)
        .saturating_mul(test_tasks as u64)
        .saturating_add(scheduled(t.train_eval_interval).saturating_mul(train_tasks as u64));
    if (eval_lines as u64) < least {
        return Err(corrupt(format!(
            "eval_lines = {eval_lines}, but iteration {iteration} implies at least {least} \
             ({test_tasks} test tasks every train.test_eval_interval = {}, {train_tasks} training \
             tasks every train.train_eval_interval = {}); the state file was edited or is \
             corrupt, and resuming would cut eval.jsonl to its count. Nothing was changed",
            t.test_eval_interval, t.train_eval_interval
        )));
    }
    Ok(())
}

/// The temporary name a checkpoint file is written under before its rename: one that
/// `pdt_base::fs::remove_stale_temps` recognises, so a kill mid-write leaves nothing behind.
pub(crate) fn temp_name(name: &str) -> String {
    format!(".{name}.tmp-{}-0", std::process::id())
}

/// What a checkpoint file is, by its name: `step_<N>.safetensors` (weights),
/// `state_<N>.safetensors` (optimiser moments) or `state_<N>.json` (training state).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CheckpointFile {
    Weights,
    Moments,
    State,
}

fn checkpoint_file(name: &str) -> Option<(CheckpointFile, u64)> {
    let (kind, rest) = if let Some(r) = name.strip_prefix("step_") {
        (CheckpointFile::Weights, r.strip_suffix(".safetensors")?)
    } else if let Some(r) = name.strip_prefix("state_") {
        match r.strip_suffix(".safetensors") {
            Some(n) => (CheckpointFile::Moments, n),
            None => (CheckpointFile::State, r.strip_suffix(".json")?),
        }
    } else {
        return None;
    };
    if rest.is_empty() || !rest.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some((kind, rest.parse().ok()?))
}

/// Removes the checkpoint files a killed run left behind, which `latest.json` does not reference:
/// the files of a checkpoint written but never committed (a step beyond the latest), optimiser
/// moments of any other step than the latest (only the latest are needed to resume), a resume
/// point's weights and state whose removal was cut short (`keep: false` in its state file, or a
/// state file without its weights; weights without a state file are kept, no kill leaves those),
/// and the temporary files of the writers of older versions (`.state_<N>.safetensors.tmp`).
/// Without `latest.json` nothing was committed: every checkpoint file goes (training starts from
/// iteration 0 and writes them again, identically). Call it only while owning the run directory.
/// Returns the names removed.
pub(crate) fn remove_orphans(ck: &Path) -> Result<Vec<String>, RunError> {
    let entries = match std::fs::read_dir(ck) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(RunError::Io { path: ck.into(), source: e }),
    };
    let latest_path = ck.join("latest.json");
    let latest: Option<Latest> = if latest_path.exists() {
        // An unreadable latest.json is refused by name when the checkpoint is loaded; until then
        // nothing can be told apart, so nothing is removed.
        match read_json(&latest_path) {
            Ok(l) => Some(l),
            Err(_) => return Ok(Vec::new()),
        }
    } else {
        None
    };
    let mut names = Vec::new();
    for entry in entries {
        let entry = entry.map_err(io_err(ck))?;
        if entry.file_type().map_err(io_err(ck))?.is_file() {
            names.push(entry.file_name().to_string_lossy().into_owned());
        }
    }
    // Whether step n's state file marks it a resume point (`keep: false`); `false` when the file
    // is missing, unreadable or older than the field (such weights are kept).
    let resume_point = |n: u64| -> bool {
        let state = ck.join(format!("state_{n}.json"));
        pdt_base::fs::read_text_limited(&state, pdt_base::fs::MAX_TEXT_BYTES)
            .ok()
            .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
            .and_then(|v| v.get("keep").and_then(serde_json::Value::as_bool))
            .is_some_and(|keep| !keep)
    };
    // Decide for every file before removing any (a state file is read to decide on its weights).
    let mut orphans = Vec::new();
    for name in names {
        let legacy_temp = name.starts_with(".step_") || name.starts_with(".state_");
        let orphan = if legacy_temp && name.ends_with(".tmp") {
            true
        } else if let Some((kind, n)) = checkpoint_file(&name) {
            match &latest {
                None => true,
                Some(l) if n == l.step => false,
                Some(l) if n > l.step => true,
                Some(_) => match kind {
                    CheckpointFile::Moments => true,
                    // `commit_checkpoint` removes a resume point's weights before its state
                    // file: a kill between leaves the state file alone.
                    CheckpointFile::Weights => resume_point(n),
                    CheckpointFile::State => {
                        resume_point(n) || !ck.join(format!("step_{n}.safetensors")).is_file()
                    }
                },
            }
        } else {
            false
        };
        if orphan {
            orphans.push(name);
        }
    }
    orphans.sort();
    for name in &orphans {
        let path = ck.join(name);
        std::fs::remove_file(&path).map_err(io_err(&path))?;
    }
    Ok(orphans)
}

/// The error of a non-finite loss or gradient: the step, the values and the likely causes.
fn diverged(dir: &Path, cfg: &TrainConfig, iteration: u64, step: u64, st: &StepStats) -> RunError {
    RunError::Invalid(format!(
        "{}: training diverged at iteration {iteration}, gradient step {step}: loss {}, gradient \
         norm {}. Likely causes: optim.learning_rate = {} too high, optim.eps = {} too small, or \
         extreme values in the data (data.dir {}). Resuming would repeat the same steps: fix the \
         configuration and train again.",
        dir.display(),
        compact(st.loss),
        compact(st.grad_norm),
        compact(cfg.optim.learning_rate),
        compact(cfg.optim.eps),
        cfg.data.dir.display()
    ))
}

/// `path` made absolute against the current directory (not resolving symlinks; the path need
/// not exist yet).
fn absolute(path: &Path) -> PathBuf {
    std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf())
}

/// Takes ownership of a run directory for this process (see `pdt_base::fs::DirLock`).
fn lock_run_dir(dir: &Path) -> Result<pdt_base::fs::DirLock, RunError> {
    pdt_base::fs::DirLock::try_acquire(dir).map_err(|e| {
        if e.kind() == std::io::ErrorKind::WouldBlock {
            RunError::Invalid(format!(
                "{} is in use by another promptdt process (it holds {}); wait for it to finish, \
                 or pick another --out",
                dir.display(),
                dir.join(".lock").display()
            ))
        } else {
            RunError::Io { path: dir.join(".lock"), source: e }
        }
    })
}

/// The identity of a new run (`run.json`).
fn run_info(setup: &Setup) -> RunInfo {
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
        split: setup.cfg.env.split.clone(),
        created: now_utc(),
        promptdt_version: env!("CARGO_PKG_VERSION").into(),
    }
}

/// Reads a run's `task_stats.json`, saying what a missing one means, and checks its values (a
/// hand-edited or corrupt file must not normalise states by NaN or 0).
pub(crate) fn read_task_stats(dir: &Path) -> Result<TaskStats, RunError> {
    let path = dir.join("task_stats.json");
    if !path.exists() {
        let why = if dir.join("checkpoints").join("latest.json").exists() {
            "but the run has a checkpoint: it cannot be recreated from today's data without \
             defeating the check that the data did not change. Restore it from a copy of the run, \
             or delete the run"
        } else {
            "the run directory was interrupted while being created (killed before writing it); \
             `promptdt train --resume` recreates it and starts the run, or delete the directory"
        };
        return Err(RunError::Invalid(format!("{} is missing, {why}", path.display())));
    }
    let stats: TaskStats = read_json(&path)?;
    stats.check().map_err(|message| RunError::Corrupt { path, message })?;
    Ok(stats)
}

fn now_utc() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    format!("unix:{secs}")
}

/// libtorch's random generator (weight init, dropout) is global to the process: runs in one process
/// take turns, so that each run's draws depend on its seed alone.
static TORCH_RNG: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub(crate) fn torch_rng_lock() -> std::sync::MutexGuard<'static, ()> {
    TORCH_RNG.lock().unwrap_or_else(|e| e.into_inner())
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
    let with = &opts.resume_with;
    let cfg = match (opts.resume, cfg) {
        (true, _) => {
            let path = dir.join("config.toml");
            if !path.is_file() {
                // `run.json` is written first: with it and no `config.toml`, a `train` was killed
                // while creating the directory, before anything that could resume it was written.
                if dir.join("checkpoints").join("latest.json").exists() {
                    return Err(RunError::Invalid(format!(
                        "{} is missing, but the run in {} has a checkpoint: restore config.toml \
                         from a copy of the run (it cannot be guessed), or delete the run",
                        path.display(),
                        dir.display()
                    )));
                }
                if dir.join("run.json").is_file() {
                    return Err(RunError::Invalid(format!(
                        "run directory {} was interrupted while being created: it has run.json \
                         but no config.toml, so there is nothing to resume; delete it or rerun \
                         `promptdt train --config <experiment> --out {}`",
                        dir.display(),
                        dir.display()
                    )));
                }
                return Err(RunError::Invalid(format!(
                    "{}: no run to resume here (no config.toml)",
                    dir.display()
                )));
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
            c
        }
        (false, None) => return Err(RunError::Invalid("no configuration given".into())),
    };
    // Refuse before anything is written, each bad setting by name.
    cfg.validate()?;
    let toml = cfg.to_toml()?;
    let setup = Setup::new(cfg)?;
    let _rng = torch_rng_lock();
    let threads = if setup.cfg.run.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        setup.cfg.run.threads
    };
    tch::set_num_threads(threads as i32);
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let _owner = lock_run_dir(dir)?;
    // Temporary files of a killed writer (we own the directory, so none is live).
    for d in [dir.to_path_buf(), dir.join("checkpoints")] {
        pdt_base::fs::remove_stale_temps(&d).map_err(io_err(&d))?;
    }
    let stats_path = dir.join("task_stats.json");
    let has_checkpoint = dir.join("checkpoints").join("latest.json").exists();
    if opts.resume && !stats_path.exists() && !has_checkpoint {
        // Killed while the directory was being created (after `config.toml`): nothing was trained
        // from it, so what is missing is recreated from the configuration and data, exactly as a
        // new run writes it, and the run starts.
        if !dir.join("run.json").is_file() {
            write_json(&dir.join("run.json"), &run_info(&setup))?;
        }
        write_json(&stats_path, &setup.stats)?;
    } else if opts.resume {
        let recorded = read_task_stats(dir)?;
        setup.stats.check_same_as(&recorded).map_err(|m| {
            RunError::Invalid(format!(
                "{}: {m}; data.dir is {}. Resume with the data the run trained on (--data DIR \
                 where it moved)",
                dir.join("task_stats.json").display(),
                setup.cfg.data.dir.display()
            ))
        })?;
    } else {
        if dir.join("checkpoints").join("latest.json").exists() {
            return Err(RunError::Invalid(format!(
                "{} already holds a run; use --resume to continue it or pick another --out",
                dir.display()
            )));
        }
        write_json(&dir.join("run.json"), &run_info(&setup))?;
        write_atomic(&dir.join("config.toml"), toml.as_bytes()).map_err(io_err(dir))?;
        write_json(&dir.join("task_stats.json"), &setup.stats)?;
    }
    // Checkpoint files a killed run left unreferenced (owning the directory makes this safe).
    remove_orphans(&dir.join("checkpoints"))?;
    if setup.cfg.run.method == Method::Macaw {
        return crate::macaw::train(&setup, dir, opts);
    }
    let cfg = &setup.cfg;
    let mut learner = Learner::new(&setup);
    let state = if opts.resume { load_checkpoint(dir, &setup, &mut learner)? } else { None };
    let (mut iteration, mut step) = state.as_ref().map_or((0, 0), |s| (s.iteration, s.step));
    if opts.resume && with.iterations.is_some() && iteration > cfg.train.iterations {
        return Err(RunError::Invalid(format!(
            "--iterations {}: the run in {} has already done {iteration} iterations; give at \
             least that many to extend it",
            cfg.train.iterations,
            dir.display()
        )));
    }
    let mut metrics = Log::open(dir, "metrics", state.as_ref().map_or(0, |s| s.metrics_lines))?;
    let mut evals = Log::open(dir, "eval", state.as_ref().map_or(0, |s| s.eval_lines))?;
    record_resume_changes(dir, cfg, with, opts.resume)?;
    let mut batch_rng = Rng::seed_from_u64(derive_seed(cfg.run.seed, STREAM_BATCHES, 0));
    if let Some(s) = &state {
        let pos = s.batch_rng_word_pos.parse::<u128>().map_err(|e| RunError::Corrupt {
            path: dir.join("checkpoints"),
            message: format!("batch_rng_word_pos: {e}"),
        })?;
        batch_rng.set_word_pos(pos);
    }
    let sampler = setup.sampler(&setup.train_data)?;
    let (t, started) = (&cfg.train, std::time::Instant::now());
    let mut last_test = None;
    let mut done_here = 0;
    while iteration < t.iterations {
        if opts.stop_after_iterations.is_some_and(|n| done_here >= n) {
            return Ok(TrainSummary {
                dir: dir.into(),
                iterations_done: iteration,
                finished: false,
                last_test,
            });
        }
        // Dropout draws come from libtorch's generator, re-seeded per iteration so that a resumed
        // run continues the same stream.
        tch::manual_seed(derive_seed(cfg.run.seed, STREAM_DROPOUT, iteration) as i64);
        let mut stats: Vec<StepStats> = Vec::with_capacity(t.steps_per_iteration as usize);
        for _ in 0..t.steps_per_iteration {
            let batch = DeviceBatch::new(
                &sampler.sample(&mut batch_rng),
                cfg.run.method.uses_prompt(),
                setup.device,
            );
            let st = train_step(&learner.model, &mut learner.opt, &batch, t.loss_on, step);
            if !(st.loss.is_finite() && st.grad_norm.is_finite()) {
                return Err(diverged(dir, cfg, iteration + 1, step, &st));
            }
            stats.push(st);
            step += 1;
        }
        iteration += 1;
        done_here += 1;
        let n = stats.len() as f64;
        let loss = stats.iter().map(|s| s.loss).sum::<f64>() / n;
        let row = serde_json::json!({
            "iteration": iteration, "step": step, "train/action_loss": loss,
            "train/grad_norm": stats.iter().map(|s| s.grad_norm).sum::<f64>() / n,
            "train/lr": stats.last().map_or(0.0, |s| s.lr), "time/elapsed_s": metrics.elapsed_before + started.elapsed().as_secs_f64(),
        });
        metrics.append(&[row.as_object().cloned().unwrap_or_default()])?;
        let last = iteration == t.iterations;
        let mut test_return = None;
        // Reference: evaluation after the first iteration and every `interval` after it.
        if (iteration - 1) % t.test_eval_interval == 0 || last {
            let res = eval_tasks(&setup, &mut learner, Split::Test, iteration)?;
            evals.append(&eval_rows(&res, iteration, step, "test", setup.stats.target_return))?;
            test_return =
                Some(res.iter().map(|r| r.return_mean).sum::<f64>() / res.len().max(1) as f64);
            last_test = Some(res);
        }
        if t.train_eval_interval > 0 && ((iteration - 1) % t.train_eval_interval == 0 || last) {
            let res = eval_tasks(&setup, &mut learner, Split::Train, iteration)?;
            evals.append(&eval_rows(&res, iteration, step, "train", setup.stats.target_return))?;
        }
        let keep = iteration % t.save_interval == 0 || last;
        if keep || (t.resume_interval > 0 && iteration % t.resume_interval == 0) {
            let state = TrainState {
                iteration,
                step,
                batch_rng_word_pos: batch_rng.get_word_pos().to_string(),
                adam_steps: learner.opt.state.iter().map(|(n, s)| (n.clone(), s.step)).collect(),
                metrics_lines: metrics.lines,
                eval_lines: evals.lines,
                keep,
            };
            save_checkpoint(dir, &learner, &state, keep)?;
        }
        (opts.progress)(&Progress { iteration, iterations: t.iterations, loss, test_return });
    }
    Ok(TrainSummary { dir: dir.into(), iterations_done: iteration, finished: true, last_test })
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
        let mut recorded = TrainConfig::from_file(&dir.join("config.toml"))?;
        recorded.train.iterations = cfg.train.iterations;
        recorded.data.dir.clone_from(&cfg.data.dir);
        let text = recorded.to_toml()?;
        write_atomic(&dir.join("config.toml"), text.as_bytes()).map_err(io_err(dir))?;
    }
    Ok(())
}

/// A finished or running run's configuration, for acting with it (`eval`, `serve`): its
/// `config.toml` with this invocation's device and the place its data moved to.
fn run_config(
    dir: &Path,
    device: Option<pdt_model::device::DeviceSpec>,
    data: Option<&Path>,
) -> Result<TrainConfig, RunError> {
    let config = dir.join("config.toml");
    if !config.is_file() {
        return Err(RunError::Invalid(format!(
            "{}: not a run directory (no config.toml)",
            dir.display()
        )));
    }
    let mut cfg = TrainConfig::from_file(&config)?;
    if let Some(d) = device {
        cfg.run.device = d;
    }
    if let Some(d) = data {
        cfg.data.dir = absolute(d);
    }
    cfg.validate()?;
    Ok(cfg)
}

/// The latest checkpoint of the run in `dir` (its weights must be the ones of its step).
pub(crate) fn latest_checkpoint(dir: &Path) -> Result<Latest, RunError> {
    let ck = dir.join("checkpoints");
    let latest: Latest = read_json(&ck.join("latest.json")).map_err(|e| match e {
        RunError::Io { .. } => {
            RunError::Invalid(format!("{}: no checkpoint yet (train first)", dir.display()))
        }
        other => other,
    })?;
    if latest.model != format!("step_{}.safetensors", latest.step) {
        return Err(RunError::Corrupt {
            path: ck.join("latest.json"),
            message: format!("names weights `{}` for step {}", latest.model, latest.step),
        });
    }
    Ok(latest)
}

/// The final evaluation of a run's latest checkpoint (`promptdt eval`), written to `eval_final.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinalEval {
    pub iteration: u64,
    pub step: u64,
    pub checkpoint: String,
    pub split: String,
    pub tasks: Vec<TaskResult>,
    pub mean_return: f64,
    /// MACAW runs: the test-time adaptation used.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptation: Option<String>,
}

/// Evaluates the latest checkpoint of the run in `dir` on its test tasks (or train tasks).
pub fn evaluate_run(
    dir: &Path,
    episodes: Option<usize>,
    split: &str,
    device: Option<pdt_model::device::DeviceSpec>,
    data: Option<&Path>,
) -> Result<FinalEval, RunError> {
    evaluate_run_with(dir, episodes, split, device, data, &MacawAdaptation::default())
}

/// A MACAW run's test-time adaptation, changed for one evaluation (`promptdt eval --adapt-steps
/// --adapt-batch`): e.g. the official protocol (1 step on 256 transitions) for a run trained with
/// the Prompt-DT one. `None` keeps the run's.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MacawAdaptation {
    pub steps: Option<usize>,
    pub batch: Option<usize>,
}

/// [`evaluate_run`] with a MACAW run's adaptation changed (refused for the other methods).
pub fn evaluate_run_with(
    dir: &Path,
    episodes: Option<usize>,
    split: &str,
    device: Option<pdt_model::device::DeviceSpec>,
    data: Option<&Path>,
    adaptation: &MacawAdaptation,
) -> Result<FinalEval, RunError> {
    let mut cfg = run_config(dir, device, data)?;
    if let Some(e) = episodes {
        cfg.eval.episodes = e;
    }
    if *adaptation != MacawAdaptation::default() {
        if cfg.run.method != Method::Macaw {
            return Err(RunError::Invalid(format!(
                "{}: --adapt-steps / --adapt-batch change a MACAW run's adaptation; this run is {}",
                dir.display(),
                cfg.run.method.name()
            )));
        }
        if let Some(n) = adaptation.steps {
            cfg.macaw.adapt_steps = n;
        }
        if let Some(b) = adaptation.batch {
            cfg.macaw.adapt_batch = b;
        }
        cfg.validate()?;
    }
    let adaptation = (cfg.run.method == Method::Macaw).then(|| {
        format!("{} steps on {} transitions", cfg.macaw.adapt_steps, cfg.macaw.adapt_batch)
    });
    let setup = Setup::new(cfg)?;
    let stats_path = dir.join("task_stats.json");
    let recorded = read_task_stats(dir)?;
    setup.stats.check_same_as(&recorded).map_err(|m| {
        RunError::Invalid(format!(
            "{}: {m}; data.dir is {}. Evaluate with the data the run trained on (--data DIR \
             where it moved)",
            stats_path.display(),
            setup.cfg.data.dir.display()
        ))
    })?;
    let which = match split {
        "test" => Split::Test,
        "train" => Split::Train,
        other => return Err(RunError::Invalid(format!("unknown split `{other}` (test or train)"))),
    };
    // A stream apart from training's evaluations, so the final numbers are not a repeat of the log.
    let (latest, tasks) = if setup.cfg.run.method == Method::Macaw {
        crate::macaw::evaluate(&setup, dir, which)?
    } else {
        let _rng = torch_rng_lock();
        let mut learner = Learner::new(&setup);
        let ck = dir.join("checkpoints");
        let latest = latest_checkpoint(dir)?;
        checkpoint::load(&mut learner.vs, &ck.join(&latest.model), setup.model_cfg.n_layer)?;
        let tasks = eval_tasks(&setup, &mut learner, which, u64::MAX - latest.iteration)?;
        (latest, tasks)
    };
    let mean_return = tasks.iter().map(|r| r.return_mean).sum::<f64>() / tasks.len().max(1) as f64;
    let result = FinalEval {
        adaptation,
        iteration: latest.iteration,
        step: latest.step,
        checkpoint: format!("checkpoints/{}", latest.model),
        split: split.into(),
        tasks,
        mean_return,
    };
    write_json(&dir.join("eval_final.json"), &result)?;
    Ok(result)
}
