//! [`Policy`]: a trained run loaded to act, and the prompts it acts with.

use crate::inputs::{finite_f32, Inputs, MAX_RETURN};
use crate::PolicyError;
use pdt_base::device::DeviceSpec;
use pdt_base::seed::derive_seed;
use pdt_eval::testtime::{plan_task, TaskPlan};
use pdt_eval::{EvalReturns, History, ToModelConfig};
use pdt_model::checkpoint;
use pdt_model::prompt_dt::Act;
use pdt_model::{PrefixCache, PromptDt};
use pdt_prompt::{BatchSampler, Rng, SegmentBatch, StateNorm};
use pdt_run::streams::{STREAM_EVAL_TEST, STREAM_EVAL_TRAIN};
use pdt_run::{eval_returns, files, RunData};
use pdt_rundir::config::{Method, TrainConfig};
use pdt_rundir::{RunDir, RunStats};
use rand::SeedableRng;
use serde::Deserialize;
use std::path::Path;
use tch::{nn::VarStore, Device};

/// A trained run, loaded to act (`promptdt serve`, the Python `Policy`): the model with its latest
/// weights and everything an episode needs besides (normalisation, return tokens, K), and, when the
/// run's data can be read, its tasks' prompt sets to draw prompts from as its evaluation does.
pub struct Policy {
    pub model: PromptDt,
    _vs: VarStore,
    pub device: Device,
    pub stats: RunStats,
    pub method: Method,
    pub k: usize,
    /// Prompt steps of a prompt drawn from the data (J x H).
    pub prompt_steps: usize,
    pub returns: EvalReturns,
    pub iteration: u64,
    /// The run's environment family (`cheetah_vel`).
    pub env: String,
    /// The state normalisation of the run's training data (from `task_stats.json`).
    pub(crate) norm: StateNorm,
    /// Task prompts, or why they are unavailable (the data could not be read or changed).
    prompts: Result<Prompts, String>,
}

/// What drawing the run's task prompts and evaluation plans needs.
struct Prompts {
    cfg: TrainConfig,
    data: RunData,
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

impl Policy {
    /// Loads the run in `dir` (latest checkpoint) on `device`; `data` overrides where its data are.
    pub fn load(
        dir: &Path,
        device: Option<DeviceSpec>,
        data: Option<&Path>,
    ) -> Result<Self, PolicyError> {
        let run = RunDir::at(dir);
        let cfg = files::run_config(&run, device, data)?;
        if !cfg.run.method.is_transformer() {
            return Err(PolicyError::NotTransformer {
                dir: dir.into(),
                method: cfg.run.method.title(),
            });
        }
        let stats = files::read_stats(&run)?;
        let family = pdt_envs::family_of_run(&cfg.env.name, &run.suite_path())?;
        let preset = family.preset();
        let model_cfg = cfg.model.to_model_config(stats.obs_dim, stats.act_dim);
        model_cfg.validate().map_err(PolicyError::Invalid)?;
        let device = pdt_torch::device::resolve(cfg.run.device)?;
        let mut vs = VarStore::new(device);
        let model = PromptDt::new(&vs.root(), &model_cfg);
        let latest = files::latest_checkpoint(&run)?;
        checkpoint::load(&mut vs, &run.checkpoint_file(&latest.model), &model_cfg)?;
        let method = cfg.run.method;
        let returns = eval_returns(&cfg);
        let prompt_steps =
            cfg.sampler.prompt_episodes * cfg.sampler.prompt_length.unwrap_or(preset.prompt_length);
        let k = cfg.sampler.k;
        let env = family.name().to_string();
        // Task prompts: the run's data, checked against what it trained on.
        let prompts =
            RunData::load(&cfg, family.as_ref()).map_err(|e| e.to_string()).and_then(|data| {
                data.stats
                    .check_same_as(&stats)
                    .map_err(|m| format!("{m}; data.dir is {}", cfg.data.dir.display()))?;
                Ok(Prompts { cfg, data })
            });
        let norm = StateNorm { mean: stats.state_mean.clone(), std: stats.state_std.clone() };
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
            norm,
            prompts,
        })
    }

    /// Whether the checkpoint, acting as loaded, is the policy the run's evaluation scores on
    /// its test tasks: not for a method that adapts to each test task first (MT-BC-Finetune), whose
    /// saved weights are its multi-task pre-training. The one check of `promptdt serve` and
    /// `promptdt render` (`command`, named in the error), so both show only what is evaluated.
    pub fn check_acts_as_evaluated(&self, command: &'static str) -> Result<(), PolicyError> {
        if !self.method.adapts_before_acting() {
            return Ok(());
        }
        let acting: Vec<&str> = Method::ALL
            .into_iter()
            .filter(|m| m.is_transformer() && !m.adapts_before_acting())
            .map(|m| m.name())
            .collect();
        Err(PolicyError::AdaptsBeforeActing {
            method: self.method.title(),
            command,
            acting: acting.join(", "),
        })
    }

    /// The state normalisation of the run's training data.
    pub fn norm(&self) -> &StateNorm {
        &self.norm
    }

    /// The settings the evaluator acts with for this policy, one episode at a time (`max_batch`
    /// 1, one environment thread, prompts through the cached prefix), on its device: what an
    /// episode acted here is compared with, bit for bit.
    pub fn eval_settings(&self) -> pdt_eval::EvalSettings {
        pdt_eval::EvalSettings {
            k: self.k,
            horizon: self.stats.horizon,
            rtg_scale: self.stats.rtg_scale,
            target_return: self.stats.target_return,
            returns: self.returns,
            norm: self.norm.clone(),
            max_batch: 1,
            device: self.device,
            env_threads: 1,
            inference: pdt_rundir::config::Inference::Cached,
        }
    }

    /// The model's longest episode (its timestep table).
    pub fn max_ep_len(&self) -> usize {
        self.model.cfg.max_ep_len
    }

    /// A prompt from arrays, checked (one entry per step in each, dims, finite values, timesteps
    /// within the model's `max_ep_len`, prompt + history within its positions), normalised as the
    /// run's data are, and then for what overflows: a state that normalises beyond f32, a
    /// return-to-go beyond [`MAX_RETURN`] (the data readers' bound). Its values go to `inputs`.
    pub fn prompt_from_arrays(
        &self,
        p: &PromptArrays,
        inputs: &mut Inputs,
    ) -> Result<SegmentBatch, PolicyError> {
        let bad = |m: String| Err(PolicyError::Input(m));
        let (ds, da) = (self.stats.obs_dim, self.stats.act_dim);
        let n = p.states.len();
        if n == 0 || n != p.actions.len() || n != p.returns_to_go.len() || n != p.timesteps.len() {
            return bad(format!(
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
            return bad(format!(
                "prompt of {n} steps: with K = {} history steps it exceeds the model's {} positions",
                self.k, self.model.cfg.n_positions
            ));
        }
        let norm = &self.norm;
        let max_t = self.model.cfg.max_ep_len as i64;
        let mut states = Vec::with_capacity(n * ds);
        let mut actions = Vec::with_capacity(n * da);
        for (t, (s, a)) in p.states.iter().zip(&p.actions).enumerate() {
            if s.len() != ds || a.len() != da {
                return bad(format!(
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
            return bad(format!(
                "prompt.timesteps: {t} is outside [0, {max_t}) (the model's max_ep_len)"
            ));
        }
        let b = SegmentBatch {
            batch: 1,
            steps: n,
            state_dim: ds,
            act_dim: da,
            states,
            actions,
            returns_to_go: rtg.iter().map(|&r| (r as f64 / scale) as f32).collect(),
            timesteps: p.timesteps.clone(),
            mask: vec![1.0; n],
        };
        for (t, s) in p.states.iter().enumerate() {
            for (j, &x) in s.iter().enumerate() {
                let z = b.states[t * ds + j];
                if !z.is_finite() {
                    return bad(format!(
                        "prompt.states[{t}][{j}] = {x:e} is out of range: normalised with the \
                         run's state statistics ((x - mean) / std, mean {}, std {}) it is beyond \
                         the largest f32 ({:e})",
                        norm.mean[j],
                        norm.std[j],
                        f32::MAX
                    ));
                }
                inputs.see(|| format!("prompt.states[{t}][{j}] = {x:e}"), z);
            }
        }
        for (t, a) in p.actions.iter().enumerate() {
            for (j, &x) in a.iter().enumerate() {
                inputs.see(|| format!("prompt.actions[{t}][{j}] = {x:e}"), b.actions[t * da + j]);
            }
        }
        for (t, &r) in p.returns_to_go.iter().enumerate() {
            if r.abs() > MAX_RETURN {
                return bad(format!(
                    "prompt.returns_to_go[{t}] = {r:e} is outside the accepted range \
                     [-{MAX_RETURN:e}, {MAX_RETURN:e}] (returns are f32 tokens)"
                ));
            }
            inputs.see(|| format!("prompt.returns_to_go[{t}] = {r:e}"), b.returns_to_go[t]);
        }
        Ok(b)
    }

    /// The keys and values of `prompts` (one row each, all of one length), computed together as
    /// the evaluator computes its tasks' prompts.
    pub fn prefix(&self, prompts: &[&SegmentBatch]) -> Result<PrefixCache, PolicyError> {
        let Some(first) = prompts.first() else {
            return Err(PolicyError::Input("no prompt given".into()));
        };
        if let Some(p) = prompts.iter().find(|p| p.steps != first.steps || p.batch != 1) {
            return Err(PolicyError::Input(format!(
                "prompts of {} and {} steps: prompts acted on together need one length",
                first.steps, p.steps
            )));
        }
        Ok(tch::no_grad(|| self.model.prefix(&pdt_eval::prompt_batch(prompts, self.device), None)))
    }

    /// The next action of each history, `[A * act_dim]`: one forward of them (with `prefix`, one
    /// row per history, or none for the methods without a prompt). Not checked: an episode's
    /// [`crate::Episode::accept`] keeps it or refuses it.
    pub fn forward(&self, histories: &[&History], prefix: Option<&PrefixCache>) -> Vec<f32> {
        self.forward_with(histories, prefix, None)
    }

    /// [`Policy::forward`] through LoRA adapters (`None`: the model as trained, the same bits).
    pub fn forward_with(
        &self,
        histories: &[&History],
        prefix: Option<&PrefixCache>,
        lora: Option<&pdt_model::LoraAdapters>,
    ) -> Vec<f32> {
        let (ds, da) = (self.stats.obs_dim, self.stats.act_dim);
        let history = pdt_eval::history_batch(histories, self.k, ds, da, self.device);
        let out = tch::no_grad(|| self.model.forward(&history, Act { prompt: prefix, lora }))
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
    pub fn eval_plan(
        &self,
        split: &str,
        episodes: Option<usize>,
    ) -> Result<Vec<TaskPlan>, PolicyError> {
        let p = self.prompts.as_ref().map_err(|why| PolicyError::Unavailable {
            what: "no evaluation plan: ",
            why: why.clone(),
        })?;
        let (data, stream) = match split {
            "test" => (&p.data.test_data, STREAM_EVAL_TEST),
            "train" => (&p.data.train_data, STREAM_EVAL_TRAIN),
            other => {
                return Err(PolicyError::Input(format!("unknown split `{other}` (test or train)")))
            }
        };
        if self.method.adapts_before_acting() && split == "test" {
            return Err(PolicyError::Input(format!(
                "{} adapts to each test task before it acts; its test evaluation has no plan to \
                 act on",
                self.method.title()
            )));
        }
        let episodes = episodes.unwrap_or(p.cfg.eval.episodes);
        if episodes == 0 {
            return Err(PolicyError::Input("episodes must be at least 1".into()));
        }
        let sampler = p.data.sampler(data)?;
        // The stream and iteration of `evaluate_run` (a final evaluation).
        let seed = derive_seed(p.cfg.run.seed, stream, u64::MAX - self.iteration);
        let mut rng = Rng::seed_from_u64(seed);
        Ok((0..data.tasks.len())
            .map(|i| plan_task(self.method, &sampler, data, i, episodes, &mut rng))
            .collect())
    }

    /// The tasks whose prompts [`Policy::task_prompt`] can draw (test tasks first), or why there
    /// are none.
    pub fn prompt_tasks(&self) -> Result<Vec<usize>, PolicyError> {
        let p = self
            .prompts
            .as_ref()
            .map_err(|why| PolicyError::Unavailable { what: "", why: why.clone() })?;
        let mut ids: Vec<usize> = p.data.test_data.tasks.iter().map(|t| t.id.index).collect();
        for t in &p.data.train_data.tasks {
            if !ids.contains(&t.id.index) {
                ids.push(t.id.index);
            }
        }
        Ok(ids)
    }

    /// A prompt of task `task` drawn as the evaluation draws one (`BatchSampler::eval_prompt`),
    /// from a generator seeded with `seed`.
    pub fn task_prompt(&self, task: usize, seed: u64) -> Result<SegmentBatch, PolicyError> {
        let sampler = self.task_sampler(task, None)?;
        Ok(sampler.eval_prompt(0, &mut Rng::seed_from_u64(seed)))
    }

    /// A sampler over task `task`'s prompt set alone (the run's sampler settings, or those of a
    /// test-time prompt `strategy`, checked to fit the model).
    pub(crate) fn task_sampler(
        &self,
        task: usize,
        strategy: Option<&pdt_prompt::PromptStrategy>,
    ) -> Result<BatchSampler<'_>, PolicyError> {
        let p = self.prompts.as_ref().map_err(|why| PolicyError::Unavailable {
            what: "no task prompts: ",
            why: why.clone(),
        })?;
        let all = p.data.test_data.tasks.iter().chain(&p.data.train_data.tasks);
        let t = all.clone().find(|t| t.id.index == task).ok_or_else(|| {
            let known = self.prompt_tasks().unwrap_or_default();
            let known: Vec<String> = known.iter().map(usize::to_string).collect();
            PolicyError::UnknownTask { task, known: known.join(", ") }
        })?;
        let n_positions = p.data.model_cfg.n_positions;
        let cfg = match strategy {
            None => p.data.sampler_cfg.clone(),
            Some(s) => pdt_prompt::strategy::check_fits(s, &p.data.sampler_cfg, n_positions)?,
        };
        Ok(BatchSampler::new(cfg, &[t], p.data.norm.clone(), n_positions)?)
    }
}
