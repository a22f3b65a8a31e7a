//! The public face of a run: [`train`] (the loop in `run_loop`, the methods in `methods`),
//! [`evaluate_run`] (the final evaluation, `evaluate`), the run directory's records (`run_dir`),
//! and [`ServedRun`], a trained run loaded to act.
//!
//! Randomness: one seed, split into independent streams (model init, batch sampling, dropout per
//! iteration, evaluation per iteration), so a resumed run draws exactly what an uninterrupted one
//! would, and evaluation never disturbs training.

pub use crate::error::RunError;
pub use crate::evaluate::{evaluate_run, evaluate_run_with};
pub use crate::methods::prompt_dt::TaskPlan;
pub use crate::methods::MacawAdaptation;
pub use crate::run_dir::{FinalEval, RunInfo, TaskStats};
pub use crate::run_loop::{train, Progress, ResumeWith, TrainOptions, TrainSummary};

use crate::config::Method;
use crate::methods::prompt_dt::plan_task;
use crate::run_dir::{latest_checkpoint, read_task_stats};
use crate::setup::Split;
use crate::setup::{eval_returns, run_config, Setup};
use crate::streams::{STREAM_EVAL_TEST, STREAM_EVAL_TRAIN};
use pdt_base::seed::derive_seed;
use pdt_eval::ToModelConfig;
use pdt_model::checkpoint;
use pdt_model::{PrefixCache, PromptDt};
use pdt_prompt::{BatchSampler, Rng, SegmentBatch, StateNorm};
use rand::SeedableRng;
use serde::Deserialize;
use std::path::Path;
use tch::{nn::VarStore, Device};

/// A trained run, loaded to act (`promptdt serve`, the Python `Policy`): the model with its latest
/// weights and everything an episode needs besides (normalisation, return tokens, K), and, when the
/// run's data can be read, its tasks' prompt sets to draw prompts from as its evaluation does.
pub struct ServedRun {
    pub model: PromptDt,
    _vs: VarStore,
    pub device: Device,
    pub stats: TaskStats,
    pub method: Method,
    pub k: usize,
    /// Prompt steps of a prompt drawn from the data (J x H).
    pub prompt_steps: usize,
    pub returns: pdt_eval::EvalReturns,
    pub iteration: u64,
    /// The run's environment family (`cheetah_vel`).
    pub env: String,
    /// `Err`: why task prompts are unavailable (the data could not be read or changed).
    prompts: Result<Setup, String>,
}

/// A prompt given as arrays (by an HTTP client or from Python): raw (unnormalised) states, the
/// actions taken, raw returns-to-go (not divided by the scale) and the demonstration's timesteps,
/// one entry per step.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PromptArrays {
    pub states: Vec<Vec<f64>>,
    pub actions: Vec<Vec<f64>>,
    pub returns_to_go: Vec<f64>,
    pub timesteps: Vec<i64>,
}

impl ServedRun {
    /// Loads the run in `dir` (latest checkpoint) on `device`; `data` overrides where its data are.
    pub fn load(
        dir: &Path,
        device: Option<pdt_model::device::DeviceSpec>,
        data: Option<&Path>,
    ) -> Result<Self, RunError> {
        let cfg = run_config(dir, device, data)?;
        if cfg.run.method == Method::Macaw {
            return Err(RunError::Invalid(format!(
                "{}: a MACAW run adapts to a task's data before it acts; serving it is not \
                 supported (evaluate it with `promptdt eval`)",
                dir.display()
            )));
        }
        let stats = read_task_stats(dir)?;
        let family = pdt_envs::family(&cfg.env.name)?;
        let preset = family.preset();
        let model_cfg = cfg.model.to_model_config(stats.obs_dim, stats.act_dim);
        model_cfg.validate().map_err(RunError::Invalid)?;
        let device = pdt_model::device::resolve(cfg.run.device)?;
        let mut vs = VarStore::new(device);
        let model = PromptDt::new(&vs.root(), &model_cfg);
        let ck = dir.join("checkpoints");
        let latest = latest_checkpoint(dir)?;
        checkpoint::load(&mut vs, &ck.join(&latest.model), model_cfg.n_layer)?;
        let method = cfg.run.method;
        let returns = eval_returns(&cfg);
        let prompt_steps =
            cfg.sampler.prompt_episodes * cfg.sampler.prompt_length.unwrap_or(preset.prompt_length);
        let k = cfg.sampler.k;
        let env = family.name().to_string();
        // Task prompts: the run's data, checked against what it trained on.
        let prompts = Setup::new(cfg).map_err(|e| e.to_string()).and_then(|setup| {
            setup
                .stats
                .check_same_as(&stats)
                .map_err(|m| format!("{m}; data.dir is {}", setup.cfg.data.dir.display()))?;
            Ok(setup)
        });
        Ok(Self {
            model,
            _vs: vs,
            device,
            stats,
            method,
            k,
            prompt_steps,
            returns,
            iteration: latest.iteration,
            env,
            prompts,
        })
    }

    /// The state normalisation of the run's training data.
    pub fn norm(&self) -> StateNorm {
        StateNorm { mean: self.stats.state_mean.clone(), std: self.stats.state_std.clone() }
    }

    /// A raw observation as f32, checked: `obs_dim` values, all finite.
    pub fn observation(&self, obs: &[f64]) -> Result<Vec<f32>, String> {
        let ds = self.stats.obs_dim;
        if obs.len() != ds {
            return Err(format!("observation has {} values, the policy takes {ds}", obs.len()));
        }
        finite_f32("observation", obs)
    }

    /// A prompt from arrays, checked (one entry per step in each, dims, finite values, timesteps
    /// within the model's `max_ep_len`, prompt + history within its positions), normalised as the
    /// run's data are.
    pub fn prompt_from_arrays(&self, p: &PromptArrays) -> Result<SegmentBatch, String> {
        let (ds, da) = (self.stats.obs_dim, self.stats.act_dim);
        let n = p.states.len();
        if n == 0 || n != p.actions.len() || n != p.returns_to_go.len() || n != p.timesteps.len() {
            return Err(format!(
                "prompt: states, actions, returns_to_go and timesteps need one entry per step \
                 (at least 1); got {}, {}, {}, {}",
                n,
                p.actions.len(),
                p.returns_to_go.len(),
                p.timesteps.len()
            ));
        }
        let k_max = self.model.cfg.n_positions / 3;
        if n + self.k > k_max {
            return Err(format!(
                "prompt of {n} steps: with K = {} history steps it exceeds the model's {} positions",
                self.k, self.model.cfg.n_positions
            ));
        }
        let norm = self.norm();
        let max_t = self.model.cfg.max_ep_len as i64;
        let mut states = Vec::with_capacity(n * ds);
        let mut actions = Vec::with_capacity(n * da);
        for (t, (s, a)) in p.states.iter().zip(&p.actions).enumerate() {
            if s.len() != ds || a.len() != da {
                return Err(format!(
                    "prompt step {t}: state has {} values and action {}, the policy takes {ds} and {da}",
                    s.len(),
                    a.len()
                ));
            }
            let s = finite_f32(&format!("prompt.states[{t}]"), s)?;
            states.extend(s.iter().enumerate().map(|(j, &x)| norm.apply(j, x)));
            actions.extend(finite_f32(&format!("prompt.actions[{t}]"), a)?);
        }
        let rtg = finite_f32("prompt.returns_to_go", &p.returns_to_go)?;
        let scale = self.stats.rtg_scale as f64;
        if let Some(t) = p.timesteps.iter().find(|&&t| !(0..max_t).contains(&t)) {
            return Err(format!(
                "prompt.timesteps: {t} is outside [0, {max_t}) (the model's max_ep_len)"
            ));
        }
        Ok(SegmentBatch {
            batch: 1,
            steps: n,
            state_dim: ds,
            act_dim: da,
            states,
            actions,
            returns_to_go: rtg.iter().map(|&r| (r as f64 / scale) as f32).collect(),
            timesteps: p.timesteps.clone(),
            mask: vec![1.0; n],
        })
    }

    /// The keys and values of `prompts` (one row each, all of one length), computed together as
    /// the evaluator computes its tasks' prompts.
    pub fn prefix(&self, prompts: &[&SegmentBatch]) -> Result<PrefixCache, String> {
        let Some(first) = prompts.first() else {
            return Err("no prompt given".into());
        };
        if let Some(p) = prompts.iter().find(|p| p.steps != first.steps || p.batch != 1) {
            return Err(format!(
                "prompts of {} and {} steps: prompts acted on together need one length",
                first.steps, p.steps
            ));
        }
        Ok(tch::no_grad(|| self.model.prefix(&pdt_eval::prompt_batch(prompts, self.device))))
    }

    /// The next action of each episode, `[A * act_dim]`: one forward of their histories (with
    /// `prefix`, one row per episode, or none for the methods without a prompt).
    pub fn act(&self, histories: &[&pdt_eval::History], prefix: Option<&PrefixCache>) -> Vec<f32> {
        let (ds, da) = (self.stats.obs_dim, self.stats.act_dim);
        let history = pdt_eval::history_batch(histories, self.k, ds, da, self.device);
        let out = tch::no_grad(|| self.model.act(&history, prefix))
            .to_kind(tch::Kind::Float)
            .to_device(Device::Cpu); // [A, da]
        let n = histories.len() * da;
        let mut flat = vec![0f32; n];
        out.contiguous().view([-1]).copy_data(&mut flat, n);
        flat
    }

    /// What `promptdt eval --split SPLIT --episodes N` draws for each task (prompt, reset seeds),
    /// in the order it evaluates them: acting with these prompts on these seeds, all episodes
    /// together, takes its actions.
    pub fn eval_plan(&self, split: &str, episodes: Option<usize>) -> Result<Vec<TaskPlan>, String> {
        let setup = self.prompts.as_ref().map_err(|why| format!("no evaluation plan: {why}"))?;
        let (data, stream, which) = match split {
            "test" => (&setup.test_data, STREAM_EVAL_TEST, Split::Test),
            "train" => (&setup.train_data, STREAM_EVAL_TRAIN, Split::Train),
            other => return Err(format!("unknown split `{other}` (test or train)")),
        };
        if self.method == Method::MtBcFinetune && which == Split::Test {
            return Err("MT-BC-Finetune fine-tunes on each test task before it acts; its test \
                        evaluation has no plan to act on"
                .into());
        }
        let episodes = episodes.unwrap_or(setup.cfg.eval.episodes);
        if episodes == 0 {
            return Err("episodes must be at least 1".into());
        }
        let sampler = setup.sampler(data).map_err(|e| e.to_string())?;
        // The stream and iteration of `evaluate_run` (a final evaluation).
        let seed = derive_seed(setup.cfg.run.seed, stream, u64::MAX - self.iteration);
        let mut rng = Rng::seed_from_u64(seed);
        Ok((0..data.tasks.len())
            .map(|i| plan_task(setup, &sampler, data, i, episodes, &mut rng))
            .collect())
    }

    /// The tasks whose prompts [`ServedRun::task_prompt`] can draw, or why there are none.
    pub fn prompt_tasks(&self) -> Result<Vec<usize>, String> {
        let setup = self.prompts.as_ref().map_err(Clone::clone)?;
        let mut ids: Vec<usize> = setup.test_data.tasks.iter().map(|t| t.id.index).collect();
        for t in &setup.train_data.tasks {
            if !ids.contains(&t.id.index) {
                ids.push(t.id.index);
            }
        }
        Ok(ids)
    }

    /// A prompt of task `task` drawn as the evaluation draws one (`BatchSampler::eval_prompt`),
    /// from a generator seeded with `seed`.
    pub fn task_prompt(&self, task: usize, seed: u64) -> Result<SegmentBatch, String> {
        let setup = self.prompts.as_ref().map_err(|why| format!("no task prompts: {why}"))?;
        let all = setup.test_data.tasks.iter().chain(&setup.train_data.tasks);
        let t = all.clone().find(|t| t.id.index == task).ok_or_else(|| {
            let known = self.prompt_tasks().unwrap_or_default();
            let known: Vec<String> = known.iter().map(usize::to_string).collect();
            format!("task {task} is not one of the run's tasks ({})", known.join(", "))
        })?;
        let sampler = BatchSampler::new(
            setup.sampler_cfg.clone(),
            &[t],
            setup.norm.clone(),
            setup.model_cfg.n_positions,
        )
        .map_err(|e| e.to_string())?;
        Ok(sampler.eval_prompt(0, &mut Rng::seed_from_u64(seed)))
    }
}

/// `values` as f32, refusing what is not finite there (a huge f64 becomes an f32 infinity).
fn finite_f32(name: &str, values: &[f64]) -> Result<Vec<f32>, String> {
    values
        .iter()
        .enumerate()
        .map(|(i, &x)| {
            let y = x as f32;
            if y.is_finite() {
                Ok(y)
            } else {
                Err(format!("{name}[{i}] = {x:e} is not a finite f32"))
            }
        })
        .collect()
}
