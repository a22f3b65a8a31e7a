//! Few-shot evaluation (`promptdt-reference.md` d, the paper's Algorithm 3), batched.
//!
//! The reference rolls out one episode at a time, one forward pass per step. Here every unfinished
//! episode of every task is stepped together: one batched forward per environment step, episodes
//! that end drop out of the batch. With `max_batch = 1` the same code is the reference's loop, and a
//! test checks that both give the same actions.
//!
//! Per episode, as the reference's `prompt_evaluate_episode_rtg` + `get_action`: the history holds
//! the states so far (normalised in f32), the actions taken (a zero placeholder for the current
//! one), returns-to-go starting at G*/scale and decreasing by r/scale, timesteps from 0; the model
//! sees the last K steps, left-padded with zeros (mask 0), and the task's prompt.
//!
//! What test time changes of that (another prompt strategy, an adaptation to each task) is
//! [`testtime`]'s: this crate is evaluation, test time included; it never trains a run's weights.

use pdt_envs::rollout::{run_batch, BatchPolicy};
use pdt_envs::vec_env::VecEnv;
use pdt_envs::{Env, EnvError, EnvFamily, StepResult};
pub mod offline;
pub mod testtime;

use pdt_base::num::compact;
use pdt_model::prompt_dt::{Act, Sequence};
use pdt_model::{LoraAdapters, PrefixCache, PromptDt, Segments};
use pdt_prompt::{SegmentBatch, StateNorm};
use pdt_rundir::config::Inference;
use pdt_rundir::files::TaskResult;
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

/// What history returns-to-go the model is fed during evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EvalReturns {
    /// G*/scale at the first step, decreasing by r/scale (the reference, all methods).
    #[default]
    Decreasing,
    /// The constant G*/scale at every step: the reference's Prompt-MT-BC evaluation (pitfall 10).
    Constant,
    /// Zero at every step, as in training with `--no-rtg`: the paper's Prompt-MT-BC.
    Zero,
}

/// One task to evaluate: its environments (one per episode) and its prompt.
pub struct EvalTask {
    pub name: String,
    pub index: usize,
    /// One environment per episode (episodes of a task may run at the same time); empty where the
    /// evaluation makes them from the family ([`evaluate_in`]).
    pub envs: Vec<Box<dyn Env>>,
    /// Reset seed of each episode.
    pub seeds: Vec<u64>,
    /// `[1, J*H]` prompt for all this task's episodes, or `None` (no-prompt variants).
    pub prompt: Option<SegmentBatch>,
    /// The G* this task's episodes are conditioned on, where the task has its own (a suite's
    /// `[[tasks]] target_return`); `None`: the settings' `target_return`.
    pub target_return: Option<f32>,
}

/// Prompts chosen per episode when it starts (the `nearest-start` strategy): given to
/// [`evaluate_with`], it replaces the tasks' shared prompts. Each episode's prompt is one row of
/// the forward (and of the cached prefix), computed once at the episode's reset.
pub trait EpisodePrompts {
    /// The `[1, J*H]` prompt of episode `episode` of task `task` (its position in the tasks
    /// passed), from the episode's first (raw) observation. All prompts have one length.
    fn at_reset(
        &mut self,
        task: usize,
        episode: usize,
        obs: &[f32],
    ) -> Result<SegmentBatch, EvalError>;
}

/// Settings shared by all tasks.
/// The model a `[model]` section describes, for an environment's dimensions. (A trait here, not a
/// method of the section: the configuration is `pdt_rundir`'s, read without libtorch.)
pub trait ToModelConfig {
    fn to_model_config(&self, state_dim: usize, act_dim: usize) -> pdt_model::PromptDtConfig;
}

impl ToModelConfig for pdt_rundir::config::ModelSection {
    fn to_model_config(&self, state_dim: usize, act_dim: usize) -> pdt_model::PromptDtConfig {
        pdt_model::PromptDtConfig {
            hidden_size: self.hidden_size,
            n_layer: self.n_layer,
            n_head: self.n_head,
            n_inner: self.n_inner,
            max_ep_len: self.max_ep_len,
            n_positions: self.n_positions,
            resid_pdrop: self.dropout,
            attn_pdrop: self.dropout,
            embd_pdrop: self.embd_dropout,
            ..pdt_model::PromptDtConfig::reference(state_dim, act_dim)
        }
    }
}

#[derive(Debug, Clone)]
pub struct EvalSettings {
    /// History length K the model sees.
    pub k: usize,
    /// Episode length limit (`max_ep_len`): episodes also end when their environment says so.
    pub horizon: usize,
    pub rtg_scale: f32,
    pub target_return: f32,
    pub returns: EvalReturns,
    pub norm: StateNorm,
    /// At most this many episodes in one forward pass (1 = the reference's sequential loop).
    pub max_batch: usize,
    pub device: Device,
    /// Threads stepping the environments of a batch (each environment is independent, so results
    /// do not depend on this number; MuJoCo steps are worth spreading, the point robot's are not).
    pub env_threads: usize,
    pub inference: Inference,
}

/// One finished episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    pub task_index: usize,
    pub seed: u64,
    pub episode_return: f64,
    pub length: usize,
    /// Whether the task counted as solved at some step of the episode (Meta-World's `success`,
    /// as its evaluations count it); `None` for families without a success criterion.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub success: Option<bool>,
    /// Actions taken, `[length * act_dim]` (kept for the batched-vs-sequential test).
    #[serde(skip)]
    pub actions: Vec<f32>,
}

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("task {task}: {source}")]
    Env { task: String, source: EnvError },
    #[error("task {task}: {why}")]
    Setup { task: String, why: String },
    /// The policy produced an action that is not finite. Caught before the environment sees it, so
    /// the message can name what the model was fed rather than only "action[0] is NaN".
    #[error("task {task}, {detail}")]
    NonFiniteAction { task: String, detail: String },
}

/// What a prompted policy remembers of one episode, as the reference's
/// `prompt_evaluate_episode_rtg` keeps it: the normalised states, the actions taken, the
/// returns-to-go. The evaluator and `promptdt serve` both act through it, so a served episode
/// takes the evaluator's actions.
#[derive(Debug, Clone, Default)]
pub struct History {
    /// Normalised states so far, `[(t+1) * ds]`.
    pub states: Vec<f32>,
    /// Actions so far, `[t * da]`.
    pub actions: Vec<f32>,
    /// Returns-to-go (already divided by the scale), `[t+1]`.
    pub rtg: Vec<f32>,
    /// Undiscounted return so far.
    pub ret: f64,
    /// Steps taken.
    pub t: usize,
}

impl History {
    /// An episode at its first observation; `first_rtg` from [`first_rtg`].
    pub fn start(norm: &StateNorm, obs: &[f32], first_rtg: f32) -> Self {
        Self { states: normalise(norm, obs), rtg: vec![first_rtg], ..Self::default() }
    }

    /// Records the action taken, the reward it earned and the observation that followed.
    pub fn record(
        &mut self,
        action: &[f32],
        reward: f32,
        obs: &[f32],
        norm: &StateNorm,
        returns: EvalReturns,
        rtg_scale: f32,
    ) {
        self.actions.extend_from_slice(action);
        self.states.extend(normalise(norm, obs));
        self.ret += reward as f64;
        let prev = *self.rtg.last().unwrap_or(&0.0);
        self.rtg.push(match returns {
            EvalReturns::Decreasing => prev - reward / rtg_scale,
            EvalReturns::Constant | EvalReturns::Zero => prev,
        });
        self.t += 1;
    }
}

/// The first return-to-go token of an episode (already divided by the scale).
pub fn first_rtg(returns: EvalReturns, target_return: f32, rtg_scale: f32) -> f32 {
    match returns {
        EvalReturns::Zero => 0.0,
        _ => target_return / rtg_scale,
    }
}

/// An episode in progress (its environment is slot `id` of the evaluation's `VecEnv`).
struct Running {
    /// Position of the episode, in (task, episode) order.
    id: usize,
    task: usize,
    /// Index of the episode within its task.
    episode: usize,
    seed: u64,
    h: History,
    /// `None` until a step reports a success criterion, then whether any step succeeded.
    success: Option<bool>,
    /// With per-episode prompts: the row of this episode's prompt in the batch's table.
    row: Option<usize>,
}

/// Normalises one raw observation in f32, as the reference does it on torch tensors at evaluation.
fn normalise(norm: &StateNorm, obs: &[f32]) -> Vec<f32> {
    obs.iter().enumerate().map(|(j, &x)| (x - norm.mean[j]) / norm.std[j]).collect()
}

/// Builds the `[A, K]` history of the given episodes (last K steps, left zero-padding).
pub fn history_batch(eps: &[&History], k: usize, ds: usize, da: usize, device: Device) -> Segments {
    let a = eps.len();
    let (mut s, mut act) = (vec![0f32; a * k * ds], vec![0f32; a * k * da]);
    let (mut r, mut ts, mut m) = (vec![0f32; a * k], vec![0i64; a * k], vec![0f32; a * k]);
    for (i, e) in eps.iter().enumerate() {
        let steps = e.t + 1; // states s_0..s_t, actions a_0..a_{t-1} plus the zero placeholder a_t
        let n = steps.min(k);
        let (first, pad) = (steps - n, k - n);
        for j in 0..n {
            let (src, dst) = (first + j, i * k + pad + j);
            s[dst * ds..(dst + 1) * ds].copy_from_slice(&e.states[src * ds..(src + 1) * ds]);
            if src < e.t {
                act[dst * da..(dst + 1) * da].copy_from_slice(&e.actions[src * da..(src + 1) * da]);
            }
            r[dst] = e.rtg[src];
            ts[dst] = src as i64;
            m[dst] = 1.0;
        }
    }
    Segments::from_host(a, k, ds, da, &s, &act, &r, &ts, &m, device)
}

/// Moves a host segment batch (`[B, L]`) to `device`.
pub fn to_segments(b: &SegmentBatch, device: Device) -> Segments {
    Segments::from_host(
        b.batch,
        b.steps,
        b.state_dim,
        b.act_dim,
        &b.states,
        &b.actions,
        &b.returns_to_go,
        &b.timesteps,
        &b.mask,
        device,
    )
}

/// Stacks the prompts of the given episodes' tasks into `[A, J*H]`.
pub fn prompt_batch(prompts: &[&SegmentBatch], device: Device) -> Segments {
    let p0 = prompts[0];
    let cat_f = |f: fn(&SegmentBatch) -> &Vec<f32>| {
        prompts.iter().flat_map(|p| f(p).iter().copied()).collect::<Vec<f32>>()
    };
    let ts: Vec<i64> = prompts.iter().flat_map(|p| p.timesteps.iter().copied()).collect();
    Segments::from_host(
        prompts.len(),
        p0.steps,
        p0.state_dim,
        p0.act_dim,
        &cat_f(|p| &p.states),
        &cat_f(|p| &p.actions),
        &cat_f(|p| &p.returns_to_go),
        &ts,
        &cat_f(|p| &p.mask),
        device,
    )
}

/// The episodes of one [`evaluate`] call as the [`run_batch`] loop drives them, a batch of up to
/// `max_batch` at a time; slot `id` is episode `id` in (task, episode) order.
struct Batch<'a> {
    model: &'a PromptDt,
    cfg: &'a EvalSettings,
    /// The prompts' keys and values, one row per task, when inference is cached.
    prefix: Option<&'a PrefixCache>,
    /// LoRA adapters every forward runs with ([`evaluate_given`]).
    lora: Option<&'a LoraAdapters>,
    prompts: &'a [Option<SegmentBatch>],
    /// Per-episode prompts of the episodes started last (rows: [`Running::row`]), and their keys
    /// and values when inference is cached. Empty without [`EpisodePrompts`].
    episode_prompts: Vec<SegmentBatch>,
    episode_prefix: Option<PrefixCache>,
    names: &'a [String],
    /// Each task's G* (its own, or the settings'), named when an action is not finite.
    targets: &'a [f32],
    /// `Some` while the episode in that slot runs.
    eps: Vec<Option<Running>>,
    /// Finished episodes, by slot.
    done: Vec<(usize, EpisodeRecord)>,
    /// The last [`Batch::task_prompts`], by the episodes' tasks: `prompts` are fixed for the
    /// evaluation, so while the same episodes run (every step of a batch of equal-length episodes)
    /// their prompts are on the device already (five uploads per step otherwise).
    task_prompt_rows: std::cell::RefCell<Option<(Vec<usize>, Option<Segments>)>>,
}

impl Batch<'_> {
    fn running(&self, slot: usize) -> Result<&Running, EvalError> {
        self.eps.get(slot).and_then(Option::as_ref).ok_or_else(|| EvalError::Setup {
            task: String::new(),
            why: format!("episode {slot} is not running (internal error)"),
        })
    }

    /// The prompts of the episodes' tasks, one row per episode (`[A, J*H]`), or `None` for tasks
    /// without prompts.
    fn task_prompts(&self, eps: &[&Running]) -> Option<Segments> {
        let tasks: Vec<usize> = eps.iter().map(|e| e.task).collect();
        let copy = |p: &Option<Segments>| p.as_ref().map(Segments::shallow_clone);
        if let Ok(last) = self.task_prompt_rows.try_borrow() {
            if let Some((_, p)) = last.as_ref().filter(|(t, _)| *t == tasks) {
                return copy(p);
            }
        }
        let rows: Option<Vec<&SegmentBatch>> =
            eps.iter().map(|e| self.prompts[e.task].as_ref()).collect();
        let made = rows.map(|p| prompt_batch(&p, self.cfg.device));
        if let Ok(mut last) = self.task_prompt_rows.try_borrow_mut() {
            *last = Some((tasks, copy(&made)));
        }
        made
    }

    /// The evaluator's own model's actions `[A, da]` for the running episodes `eps`.
    fn forward_own(&self, eps: &[&Running], history: &Segments) -> Tensor {
        let (cfg, model) = (self.cfg, self.model);
        let per_episode: Option<Vec<usize>> = eps.iter().map(|e| e.row).collect();
        match (cfg.inference, self.prefix, per_episode) {
            (Inference::Cached, _, Some(rows)) if self.episode_prefix.is_some() => {
                let rows: Vec<i64> = rows.iter().map(|&r| r as i64).collect();
                let rows = Tensor::from_slice(&rows).to_device(cfg.device);
                let c = self.episode_prefix.as_ref().map(|c| c.select(&rows));
                tch::no_grad(|| model.forward(history, Act { prompt: c.as_ref(), lora: None }))
                // [A, da]
            }
            (_, _, Some(rows)) => {
                let p: Vec<&SegmentBatch> =
                    rows.iter().map(|&r| &self.episode_prompts[r]).collect();
                let prompt = prompt_batch(&p, cfg.device);
                let preds = tch::no_grad(|| model.forward(history, Sequence::eval(Some(&prompt)))); // [A, K, da]
                preds.select(1, cfg.k as i64 - 1) // [A, da]
            }
            (Inference::Cached, Some(c), None) => {
                let rows: Vec<i64> = eps.iter().map(|e| e.task as i64).collect();
                let rows = Tensor::from_slice(&rows).to_device(cfg.device);
                tch::no_grad(|| {
                    model.forward(history, Act { prompt: Some(&c.select(&rows)), lora: self.lora })
                })
                // [A, da]
            }
            (Inference::Cached, None, None) if self.prompts.iter().all(Option::is_none) => {
                tch::no_grad(|| model.forward(history, Act { prompt: None, lora: None }))
                // [A, da]
            }
            _ => {
                let prompt = self.task_prompts(eps);
                let preds =
                    tch::no_grad(|| model.forward(history, Sequence::eval(prompt.as_ref()))); // [A, K, da]
                preds.select(1, cfg.k as i64 - 1) // [A, da]
            }
        }
    }
}

impl BatchPolicy for Batch<'_> {
    type Error = EvalError;

    fn act(&mut self, slots: &[usize]) -> Result<Vec<f32>, EvalError> {
        let (cfg, model) = (self.cfg, self.model);
        let (ds, da) = (model.cfg.state_dim, model.cfg.act_dim);
        let eps: Vec<&Running> =
            slots.iter().map(|&s| self.running(s)).collect::<Result<_, _>>()?;
        let hs: Vec<&History> = eps.iter().map(|e| &e.h).collect();
        let history = history_batch(&hs, cfg.k, ds, da, cfg.device);
        let last = self.forward_own(&eps, &history).to_kind(Kind::Float).to_device(Device::Cpu);
        let mut acts = vec![0f32; eps.len() * da];
        last.contiguous().view([-1]).copy_data(&mut acts, eps.len() * da);
        // A non-finite action is the model's failure, not the environment's: say what it was fed.
        if let Some(i) = acts.iter().position(|a| !a.is_finite()) {
            let ep = eps[i / da];
            let detail = format!(
                "episode {} (reset seed {}), step {}: the policy's action[{}] is {}, not \
                 finite. The return token was {} (eval.target_return = {} over rtg_scale = {} \
                 at the first step): a token far outside the training data's range makes the \
                 model overflow f32. Other causes: absurd (huge but finite) weights in the \
                 checkpoint, or absurd state statistics",
                ep.episode,
                ep.seed,
                ep.h.t,
                i % da,
                acts[i],
                compact(ep.h.rtg.last().copied().unwrap_or(0.0)),
                compact(self.targets[ep.task]),
                compact(cfg.rtg_scale)
            );
            return Err(EvalError::NonFiniteAction { task: self.names[ep.task].clone(), detail });
        }
        Ok(acts)
    }

    fn record(
        &mut self,
        slot: usize,
        action: &[f32],
        step: Result<StepResult, EnvError>,
    ) -> Result<bool, EvalError> {
        let cfg = self.cfg;
        let Some(mut ep) = self.eps.get_mut(slot).and_then(Option::take) else {
            let why = format!("episode {slot} is not running (internal error)");
            return Err(EvalError::Setup { task: String::new(), why });
        };
        let step =
            step.map_err(|source| EvalError::Env { task: self.names[ep.task].clone(), source })?;
        ep.h.record(action, step.reward, &step.obs, &cfg.norm, cfg.returns, cfg.rtg_scale);
        if let Some(ok) = step.success {
            ep.success = Some(ep.success.unwrap_or(false) || ok);
        }
        if step.terminated || step.truncated || ep.h.t >= cfg.horizon {
            let record = EpisodeRecord {
                task_index: ep.task,
                seed: ep.seed,
                episode_return: ep.h.ret,
                length: ep.h.t,
                success: ep.success,
                actions: ep.h.actions,
            };
            self.done.push((ep.id, record));
            return Ok(true);
        }
        self.eps[slot] = Some(ep);
        Ok(false)
    }

    /// A failure of the pool itself (not of one environment) is charged to the batch's tasks.
    fn batch_error(&self, slots: &[usize], source: EnvError) -> EvalError {
        let mut tasks: Vec<&str> = slots
            .iter()
            .filter_map(|&s| self.eps.get(s).and_then(Option::as_ref))
            .map(|e| self.names[e.task].as_str())
            .collect();
        tasks.dedup();
        EvalError::Env { task: tasks.join(", "), source }
    }
}

/// Runs every episode of every task to its end; returns the episodes in (task, episode) order.
///
/// All episodes' environments go into one [`VecEnv`] on `cfg.env_threads` threads, started once
/// for the call; each forward's actions step only the episodes still running (a masked step).
pub fn evaluate(
    model: &PromptDt,
    tasks: Vec<EvalTask>,
    cfg: &EvalSettings,
) -> Result<Vec<EpisodeRecord>, EvalError> {
    evaluate_with(model, tasks, cfg, None)
}

/// [`evaluate`], with each episode's prompt chosen at its reset by `chooser` when given (the
/// tasks' own prompts are then not used). Episodes are still stepped together; each batch's new
/// prompts go through the model's prefix in one forward.
pub fn evaluate_with(
    model: &PromptDt,
    tasks: Vec<EvalTask>,
    cfg: &EvalSettings,
    chooser: Option<&mut dyn EpisodePrompts>,
) -> Result<Vec<EpisodeRecord>, EvalError> {
    evaluate_inner(model, tasks, cfg, chooser, None, None)
}

/// An evaluation whose episodes' environments `family` makes, all at once, when it starts
/// ([`EnvFamily::make_batch`]: on this process's threads for the built-in families, in a Python
/// worker for a suite's own environment); the tasks' `envs` are then empty and their `index` is
/// the family's task. With `chooser` and `given` as in [`evaluate_with`] and [`evaluate_given`].
pub fn evaluate_in(
    family: &dyn EnvFamily,
    model: &PromptDt,
    tasks: Vec<EvalTask>,
    cfg: &EvalSettings,
    chooser: Option<&mut dyn EpisodePrompts>,
    given: Option<GivenPrompts<'_>>,
) -> Result<Vec<EpisodeRecord>, EvalError> {
    match given {
        None => evaluate_inner(model, tasks, cfg, chooser, None, Some(family)),
        Some(given) => {
            let cfg = given_settings(&given, tasks.len(), cfg)?;
            evaluate_inner(model, tasks, &cfg, chooser, Some(given), Some(family))
        }
    }
}

/// What an adapted evaluation acts with in place of the tasks' prompts: the prompts' keys and
/// values (one row per task, in task order; from tuned prompt tokens) and optional LoRA
/// adapters, computed by the caller with the same adapters (`adapt`).
pub struct GivenPrompts<'a> {
    pub prefix: PrefixCache,
    pub lora: Option<&'a LoraAdapters>,
}

/// [`evaluate`] with the prompts given as a prefix (and optional adapters), always through the
/// cached path (the prefix is all there is of the prompt).
pub fn evaluate_given(
    model: &PromptDt,
    tasks: Vec<EvalTask>,
    cfg: &EvalSettings,
    given: GivenPrompts<'_>,
) -> Result<Vec<EpisodeRecord>, EvalError> {
    let cfg = given_settings(&given, tasks.len(), cfg)?;
    evaluate_inner(model, tasks, &cfg, None, Some(given), None)
}

/// The settings of an evaluation with `given` prompts for `tasks` tasks: the cached path.
fn given_settings(
    given: &GivenPrompts<'_>,
    tasks: usize,
    cfg: &EvalSettings,
) -> Result<EvalSettings, EvalError> {
    if given.prefix.rows() != tasks as i64 {
        let why =
            format!("{} given prompt rows for {tasks} tasks (internal error)", given.prefix.rows());
        return Err(EvalError::Setup { task: String::new(), why });
    }
    Ok(EvalSettings { inference: Inference::Cached, ..cfg.clone() })
}

fn evaluate_inner(
    model: &PromptDt,
    tasks: Vec<EvalTask>,
    cfg: &EvalSettings,
    mut chooser: Option<&mut dyn EpisodePrompts>,
    given: Option<GivenPrompts<'_>>,
    family: Option<&dyn EnvFamily>,
) -> Result<Vec<EpisodeRecord>, EvalError> {
    let (ds, da) = (model.cfg.state_dim, model.cfg.act_dim);
    let mut names: Vec<String> = Vec::with_capacity(tasks.len());
    let mut targets: Vec<f32> = Vec::with_capacity(tasks.len());
    let mut prompts: Vec<Option<SegmentBatch>> = Vec::with_capacity(tasks.len());
    let mut envs: Vec<Box<dyn Env>> = Vec::new();
    // With a family: the family's task of each episode, whose environment it makes.
    let mut family_tasks: Vec<usize> = Vec::new();
    let mut queue: Vec<Running> = Vec::new();
    for (ti, task) in tasks.into_iter().enumerate() {
        let wanted = if family.is_some() { 0 } else { task.seeds.len() };
        if task.envs.len() != wanted {
            let why = match family {
                None => "one seed per environment is needed",
                Some(_) => "environments given where the family makes them (internal error)",
            };
            return Err(EvalError::Setup { task: task.name, why: why.into() });
        }
        for env in &task.envs {
            check_dims(&task.name, env.obs_dim(), env.act_dim(), ds, da)?;
        }
        envs.extend(task.envs);
        for (episode, seed) in task.seeds.into_iter().enumerate() {
            let id = queue.len();
            queue.push(Running {
                id,
                task: ti,
                episode,
                seed,
                h: History::default(),
                success: None,
                row: None,
            });
            if family.is_some() {
                family_tasks.push(task.index);
            }
        }
        names.push(task.name);
        prompts.push(task.prompt);
        targets.push(task.target_return.unwrap_or(cfg.target_return));
    }
    let n = queue.len();
    // The prompts' keys and values, once per task (all tasks have a prompt or none does).
    let all_prompts: Option<Vec<&SegmentBatch>> = prompts.iter().map(Option::as_ref).collect();
    let lora = given.as_ref().and_then(|g| g.lora);
    let prefix = match (cfg.inference, all_prompts) {
        _ if given.is_some() => given.map(|g| g.prefix),
        (Inference::Cached, Some(all)) if !all.is_empty() && chooser.is_none() => {
            Some(tch::no_grad(|| model.prefix(&prompt_batch(&all, cfg.device), None)))
        }
        _ => None,
    };
    let mut venv = match family {
        None => VecEnv::new(envs, cfg.env_threads),
        Some(f) => family_batch(f, &family_tasks, &names, &queue, cfg, (ds, da))?,
    };
    let mut batch = Batch {
        model,
        cfg,
        prefix: prefix.as_ref(),
        lora,
        prompts: &prompts,
        episode_prompts: Vec::new(),
        episode_prefix: None,
        names: &names,
        targets: &targets,
        eps: (0..n).map(|_| None).collect(),
        done: Vec::with_capacity(n),
        task_prompt_rows: Default::default(),
    };
    let mut queue = queue.into_iter().peekable();
    while queue.peek().is_some() {
        // Start up to `max_batch` episodes, in episode order; they run to their ends together.
        let mut slots = Vec::with_capacity(cfg.max_batch.max(1));
        let mut resets = Vec::with_capacity(cfg.max_batch.max(1));
        for ep in queue.by_ref().take(cfg.max_batch.max(1)) {
            slots.push(ep.id);
            resets.push((ep.id, ep.seed));
            let id = ep.id;
            batch.eps[id] = Some(ep);
        }
        let first = venv.reset_some(&resets).map_err(|source| batch.batch_error(&slots, source))?;
        let mut chosen = Vec::new();
        for (&id, obs) in slots.iter().zip(first) {
            if let Some(ep) = batch.eps[id].as_mut() {
                let rtg = first_rtg(cfg.returns, targets[ep.task], cfg.rtg_scale);
                ep.h = History::start(&cfg.norm, &obs, rtg);
                if let Some(c) = chooser.as_deref_mut() {
                    ep.row = Some(chosen.len());
                    chosen.push(c.at_reset(ep.task, ep.episode, &obs)?);
                }
            }
        }
        if !chosen.is_empty() {
            batch.episode_prefix = episode_prefix(model, cfg, &chosen)?;
            batch.episode_prompts = chosen;
        }
        run_batch(&mut venv, slots, &mut batch)?;
    }
    let mut done = batch.done;
    // Episodes of a batch end in any order; report them in (task, episode) order.
    done.sort_by_key(|(id, _)| *id);
    Ok(done.into_iter().map(|(_, r)| r).collect())
}

/// The prefix of the prompts `chosen` for a batch's episodes (one each, all of one length), on the
/// cached path; `None` on the full one.
fn episode_prefix(
    model: &PromptDt,
    cfg: &EvalSettings,
    chosen: &[SegmentBatch],
) -> Result<Option<PrefixCache>, EvalError> {
    if let Some(p) = chosen.iter().find(|p| p.steps != chosen[0].steps || p.batch != 1) {
        let why = format!(
            "per-episode prompts of {} and {} steps: one length is needed",
            chosen[0].steps, p.steps
        );
        return Err(EvalError::Setup { task: String::new(), why });
    }
    let refs: Vec<&SegmentBatch> = chosen.iter().collect();
    Ok(match cfg.inference {
        Inference::Cached => {
            Some(tch::no_grad(|| model.prefix(&prompt_batch(&refs, cfg.device), None)))
        }
        Inference::Full => None,
    })
}

/// The family's environments of the episodes `queue` (`tasks[i]`: episode `i`'s task), each of
/// the model's sizes `(obs, act)`; an error names the tasks of the batch.
fn family_batch(
    family: &dyn EnvFamily,
    tasks: &[usize],
    names: &[String],
    queue: &[Running],
    cfg: &EvalSettings,
    (ds, da): (usize, usize),
) -> Result<VecEnv, EvalError> {
    let all: Vec<usize> = (0..queue.len()).collect();
    let charge = |source| EvalError::Env { task: task_names(names, queue, &all), source };
    let venv = family.make_batch(tasks, cfg.env_threads).map_err(charge)?;
    for (d, ep) in venv.dims().iter().zip(queue) {
        check_dims(&names[ep.task], d.obs_dim, d.act_dim, ds, da)?;
    }
    Ok(venv)
}

/// Refuses an environment of other sizes than the model's.
fn check_dims(task: &str, obs: usize, act: usize, ds: usize, da: usize) -> Result<(), EvalError> {
    if (obs, act) == (ds, da) {
        return Ok(());
    }
    let why = format!("environment dims {obs}/{act} differ from the model's {ds}/{da}");
    Err(EvalError::Setup { task: task.to_owned(), why })
}

/// The distinct names of the tasks of `episodes` (queue positions), joined.
fn task_names(names: &[String], queue: &[Running], episodes: &[usize]) -> String {
    let mut out: Vec<&str> =
        episodes.iter().filter_map(|&i| queue.get(i)).map(|e| names[e.task].as_str()).collect();
    out.dedup();
    out.join(", ")
}

/// Mean, population std and mean length of a task's episodes.
pub fn summarise(name: &str, task_index: usize, episodes: &[&EpisodeRecord]) -> TaskResult {
    let returns: Vec<f64> = episodes.iter().map(|e| e.episode_return).collect();
    let n = returns.len().max(1) as f64;
    let mean = returns.iter().sum::<f64>() / n;
    let std = (returns.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / n).sqrt();
    let length_mean = episodes.iter().map(|e| e.length as f64).sum::<f64>() / n;
    // A rate only where every episode reports one (a family has a success criterion or not).
    let wins: Option<Vec<bool>> = episodes.iter().map(|e| e.success).collect();
    let success_rate = wins
        .filter(|w| !w.is_empty())
        .map(|w| w.iter().filter(|&&ok| ok).count() as f64 / w.len() as f64);
    TaskResult {
        task: name.to_string(),
        task_index,
        return_mean: mean,
        return_std: std,
        length_mean,
        episodes: returns.len(),
        returns,
        success_rate,
    }
}

/// A tensor's values, for tests and reports.
pub fn to_vec(t: &Tensor) -> Vec<f32> {
    let t = t.to_kind(Kind::Float).to_device(Device::Cpu).contiguous().view([-1]);
    let mut v = vec![0f32; t.numel()];
    let n = v.len();
    t.copy_data(&mut v, n);
    v
}
