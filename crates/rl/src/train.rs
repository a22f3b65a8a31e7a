//! The training loop behind `promptdt collect`: one task-conditioned agent per family (a task drawn
//! per episode), one environment step then `updates_per_step` gradient updates, checkpoints at
//! episode ends, and actor snapshots along the way (the medium policy is one of them).
//!
//! Every random choice has its own stream keyed by a counter (episode, env step, update), so a run
//! resumed from a checkpoint takes exactly the steps the uninterrupted run takes.
//!
//! Run directory:
//! - `config.json`: the [`RlConfig`].
//! - `checkpoint.safetensors`: agent, optimiser moments, replay buffer, and the [`TrainState`] in
//!   the metadata; written atomically at episode ends every `checkpoint_every` steps.
//! - `episodes.csv`: one row per finished training episode.
//! - `snapshots/actor-{step}.safetensors`: actor snapshots (policy files) with their evaluation.
//! - `agent/`: at the end, `expert.safetensors`, `medium.safetensors` and `agent.json` — what
//!   `pretrained/<family>/` holds.

use crate::agent::{Agent, AgentConfig, Algorithm, CollectPreset, Noise, TaskEncoder, UpdateStats};
use crate::buffer::{BufferArrays, ReplayBuffer};
use crate::policy::{self, PolicyMeta, POLICY_FORMAT};
use crate::rollout::{run_episodes, Behaviour, EpisodeSpec};
use crate::{stream_rng, write_atomic, RlError};
use pdt_base::tensor_file::describe_safetensors_error;
use pdt_envs::EnvFamily;
use rand::Rng;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use tch::Device;

mod episode;

use episode::{Learning, Played, World};

const STREAM_INIT: u64 = 1;
const STREAM_EPISODE: u64 = 2;
const STREAM_ACT: u64 = 3;
const STREAM_BATCH: u64 = 4;
const STREAM_EVAL: u64 = 5;

pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";
const STATE_KEY: &str = "promptdt_rl_state";

/// Everything that defines a training run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RlConfig {
    pub family: String,
    pub algorithm: Algorithm,
    pub seed: u64,
    /// Environment steps in all.
    pub total_steps: u64,
    /// Uniform random actions for this many first steps, and no updates before.
    pub learning_starts: u64,
    pub batch_size: usize,
    pub updates_per_step: u64,
    /// Minibatches from the most recent this many transitions only; 0: the whole buffer. For
    /// fine-tuning on a few tasks (`Start::Resume { tasks, .. }`), whose buffer is otherwise
    /// mostly the earlier tasks' transitions.
    #[serde(default)]
    pub sample_recent: u64,
    /// Tasks the agent trains on (one drawn uniformly per episode); empty: all of the family's.
    /// A single task gives a per-task agent.
    #[serde(default)]
    pub tasks: Vec<usize>,
    /// Checkpoint at the first episode end after every this many steps.
    pub checkpoint_every: u64,
    /// Fractions of `total_steps` at which the actor is snapshotted and evaluated.
    pub snapshot_fractions: Vec<f64>,
    /// Deterministic evaluation episodes per task for each snapshot.
    pub eval_episodes: usize,
    #[serde(default)]
    pub agent: AgentConfig,
}

impl RlConfig {
    /// The settings used for the committed experts (and a starting point for others).
    ///
    /// Networks are 128 x 128 rather than the SAC paper's 256 x 256: an update then costs about a
    /// third (a 2-core CPU is the budget these experts were trained on), and
    /// these locomotion tasks do not need more.
    pub fn preset(family: &str) -> Result<Self, RlError> {
        let fam = pdt_envs::family(family)?;
        // The algorithm and budget are the family's (configs/collect/<family>.toml).
        let CollectPreset { algorithm, total_steps, .. } = CollectPreset::of(fam.as_ref())?;
        let mut agent = AgentConfig::default();
        agent.sac.hidden = vec![128, 128];
        agent.td3.hidden = vec![128, 128];
        Ok(Self {
            family: fam.name().to_string(),
            algorithm,
            seed: 0,
            total_steps,
            learning_starts: 5_000.min(total_steps / 4),
            batch_size: 256,
            updates_per_step: 1,
            sample_recent: 0,
            tasks: vec![],
            checkpoint_every: 50_000,
            snapshot_fractions: vec![
                0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0,
            ],
            eval_episodes: 1,
            agent,
        })
    }

    pub fn validate(&self, family: &dyn EnvFamily) -> Result<(), RlError> {
        let bad = |m: String| Err(RlError::Config(m));
        if self.total_steps == 0 {
            return bad("total_steps must be at least 1".into());
        }
        if self.batch_size == 0 {
            return bad("batch_size must be at least 1".into());
        }
        if self.checkpoint_every == 0 {
            return bad("checkpoint_every must be at least 1".into());
        }
        if self.eval_episodes == 0 {
            return bad("eval_episodes must be at least 1".into());
        }
        if self.snapshot_fractions.iter().any(|f| !(*f > 0.0 && *f <= 1.0)) {
            return bad(format!(
                "snapshot_fractions must lie in (0, 1]: {:?}",
                self.snapshot_fractions
            ));
        }
        for &t in &self.tasks {
            if t >= family.num_tasks() {
                return Err(pdt_envs::EnvError::UnknownTask {
                    env: family.name().into(),
                    task: t,
                    n: family.num_tasks(),
                }
                .into());
            }
        }
        let h = &self.agent;
        if h.sac.hidden.is_empty()
            || h.td3.hidden.is_empty()
            || h.sac.hidden.iter().chain(&h.td3.hidden).any(|&s| s < 1)
        {
            return bad("hidden layer sizes must be positive and non-empty".into());
        }
        Ok(())
    }

    fn train_tasks(&self, family: &dyn EnvFamily) -> Vec<usize> {
        if self.tasks.is_empty() {
            (0..family.num_tasks()).collect()
        } else {
            self.tasks.clone()
        }
    }

    /// Environment step at which snapshot `k` is due.
    fn snapshot_steps(&self) -> Vec<u64> {
        let mut s: Vec<u64> = self
            .snapshot_fractions
            .iter()
            .map(|f| ((f * self.total_steps as f64).round() as u64).clamp(1, self.total_steps))
            .collect();
        s.push(self.total_steps);
        s.sort_unstable();
        s.dedup();
        s
    }
}

/// One finished training episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeLog {
    pub episode: u64,
    /// Environment steps done when it ended.
    pub step: u64,
    pub task: usize,
    pub episode_return: f64,
    pub length: usize,
}

/// An evaluated actor snapshot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SnapshotInfo {
    pub step: u64,
    pub file: String,
    /// Mean deterministic return per task of the family.
    pub eval_returns: Vec<f64>,
    pub mean_return: f64,
}

/// The resumable state besides tensors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    pub config: RlConfig,
    pub step: u64,
    pub episode: u64,
    pub updates: u64,
    pub episodes: Vec<EpisodeLog>,
    pub snapshots: Vec<SnapshotInfo>,
    pub optimiser_steps: Vec<(String, u64)>,
    pub wall_seconds: f64,
}

/// What the progress callback sees.
#[derive(Debug, Clone)]
pub struct TrainProgress<'a> {
    pub step: u64,
    pub total: u64,
    pub episode: u64,
    pub updates: u64,
    /// Mean of the last few episode returns per training task (`None` before its first episode).
    pub recent: &'a [Option<f64>],
    pub last_update: UpdateStats,
    /// Set when a snapshot was just evaluated.
    pub snapshot: Option<&'a SnapshotInfo>,
}

/// What `agent/agent.json` records.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AgentCard {
    pub format: String,
    pub family: String,
    pub algorithm: Algorithm,
    pub config: RlConfig,
    pub expert_step: u64,
    pub medium_step: u64,
    /// Deterministic evaluation per task: uniform random actions, the medium and expert snapshots.
    pub random_eval: Vec<f64>,
    pub medium_eval: Vec<f64>,
    pub expert_eval: Vec<f64>,
    pub snapshots: Vec<SnapshotInfo>,
    pub wall_seconds: f64,
    pub why_medium: String,
    /// When the experts differ by task (an agent made by [`crate::combine`]): the policy file of
    /// each task. Empty: `expert.safetensors` for every task.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub task_experts: Vec<TaskExpert>,
    /// How `collect` writes this agent's datasets unless told otherwise (`None`: exploration
    /// noise, as in a replay buffer).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dataset_noise: Option<Noise>,
}

/// The expert of one task in a combined agent.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskExpert {
    pub task: usize,
    /// Policy file in the agent directory.
    pub file: String,
    /// The snapshot it was copied from.
    pub source: String,
    /// The mirror it acts through, if any (see `agent::Mirror`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mirror: Option<String>,
    /// Its training step.
    pub step: u64,
    /// Its mean deterministic return on the task, over the combination's evaluation episodes.
    pub eval_return: f64,
}

impl AgentCard {
    /// The expert policy file of `task`.
    pub fn expert_file(&self, task: usize) -> &str {
        self.task_experts
            .iter()
            .find(|e| e.task == task)
            .map_or("expert.safetensors", |e| e.file.as_str())
    }
}

pub const AGENT_CARD_FORMAT: &str = "promptdt-agent-v1";

/// How [`train`] starts.
#[derive(Debug, Clone, Copy)]
pub enum Start<'a> {
    /// A new run in an empty (or missing) directory.
    New(&'a RlConfig),
    /// Continue from the directory's checkpoint, optionally with a new (larger) step budget and a
    /// new set of training tasks (fine-tuning a trained agent on the tasks it does worst, say; the
    /// replay buffer keeps the earlier tasks' transitions).
    /// `sample_recent` likewise replaces the minibatch window.
    Resume { total_steps: Option<u64>, tasks: Option<&'a [usize]>, sample_recent: Option<u64> },
}

/// Trains (or resumes) in `dir`; at the end writes `dir/agent/`.
/// `stop_after` stops after this many environment steps of this call, at an episode end, with a
/// checkpoint written, exactly as if the process had been killed after that checkpoint.
pub fn train(
    start: Start<'_>,
    dir: &Path,
    stop_after: Option<u64>,
    device: Device,
    progress: &mut dyn FnMut(&TrainProgress<'_>),
) -> Result<Option<AgentCard>, RlError> {
    let ckpt_path = dir.join(CHECKPOINT_FILE);
    let (cfg, loaded) = open(start, dir, &ckpt_path)?;
    let family = pdt_envs::family(&cfg.family)?;
    cfg.validate(family.as_ref())?;
    let encoder = TaskEncoder::for_family(family.as_ref())?;
    let preset = family.preset();
    let (in_dim, act_dim) = (encoder.input_dim(), preset.act_dim);
    std::fs::create_dir_all(dir.join("snapshots"))
        .map_err(|source| RlError::Io { path: dir.to_path_buf(), source })?;
    let cfg_text =
        serde_json::to_string_pretty(&cfg).map_err(|e| RlError::Config(e.to_string()))?;
    write_atomic(&dir.join("config.json"), cfg_text.as_bytes())?;

    let mut agent = Agent::new(
        cfg.algorithm,
        in_dim,
        act_dim,
        &cfg.agent,
        &mut stream_rng(cfg.seed, STREAM_INIT, 0),
        device,
    );
    let (mut state, buffer) = restore(loaded, &mut agent, &cfg, (in_dim, act_dim), &ckpt_path)?;
    state.config = cfg.clone();

    let tasks = cfg.train_tasks(family.as_ref());
    let mut recent: Vec<VecDeque<f64>> = vec![VecDeque::new(); tasks.len()];
    for log in &state.episodes {
        if let Some(k) = tasks.iter().position(|&t| t == log.task) {
            push_recent(&mut recent[k], log.episode_return);
        }
    }
    let snapshot_steps = cfg.snapshot_steps();
    let mut next_ckpt = (state.step / cfg.checkpoint_every + 1) * cfg.checkpoint_every;
    let start_step = state.step;
    let started = std::time::Instant::now();
    let wall_before = state.wall_seconds;
    let world = World {
        cfg: &cfg,
        family: family.as_ref(),
        encoder: &encoder,
        tasks: &tasks,
        act_dim,
        device,
    };
    let mut l = Learning {
        agent,
        buffer,
        state,
        last_update: UpdateStats::default(),
        envs: (0..family.num_tasks()).map(|_| None).collect(),
        x: Vec::with_capacity(in_dim),
        x_next: Vec::with_capacity(in_dim),
        action: Vec::with_capacity(act_dim),
    };

    while l.state.step < cfg.total_steps {
        let Played { task, ret, len } = l.episode(&world)?;
        let state = &mut l.state;
        state.episodes.push(EpisodeLog {
            episode: state.episode,
            step: state.step,
            task,
            episode_return: ret,
            length: len,
        });
        if let Some(k) = tasks.iter().position(|&t| t == task) {
            push_recent(&mut recent[k], ret);
        }
        state.episode += 1;

        // Snapshots due by now (at most one per episode end).
        let mut snap = None;
        // The next scheduled step after the last snapshot taken (by step, not by count, so that a
        // run resumed with a larger budget keeps snapshotting on its new schedule).
        let last_snap = state.snapshots.last().map_or(0, |s| s.step);
        if let Some(&due) = snapshot_steps.iter().find(|&&s| s > last_snap) {
            if state.step >= due {
                let info =
                    snapshot(&cfg, family.as_ref(), &encoder, &l.agent, state.step, dir, device)?;
                state.snapshots.push(info);
                snap = state.snapshots.last();
            }
        }
        let recent_means: Vec<Option<f64>> = recent
            .iter()
            .map(|r| (!r.is_empty()).then(|| r.iter().sum::<f64>() / r.len() as f64))
            .collect();
        progress(&TrainProgress {
            step: state.step,
            total: cfg.total_steps,
            episode: state.episode,
            updates: state.updates,
            recent: &recent_means,
            last_update: l.last_update,
            snapshot: snap,
        });
        let stop = stop_after.is_some_and(|m| state.step - start_step >= m);
        if state.step >= next_ckpt || state.step >= cfg.total_steps || stop {
            state.wall_seconds = wall_before + started.elapsed().as_secs_f64();
            write_checkpoint(&ckpt_path, state, &l.agent, &l.buffer)?;
            write_episodes_csv(&dir.join("episodes.csv"), &state.episodes)?;
        }
        if state.step >= next_ckpt || state.step >= cfg.total_steps {
            next_ckpt = (state.step / cfg.checkpoint_every + 1) * cfg.checkpoint_every;
        }
        if stop && state.step < cfg.total_steps {
            return Ok(None);
        }
    }
    let state = &mut l.state;
    state.wall_seconds = wall_before + started.elapsed().as_secs_f64();
    finish(&cfg, family.as_ref(), state, dir).map(Some)
}

/// The run's configuration, and its checkpoint where it resumes (with the budget, tasks and window
/// a resume may change); a new run refused where `dir` already holds one.
#[allow(clippy::type_complexity)]
fn open(
    start: Start<'_>,
    dir: &Path,
    ckpt_path: &Path,
) -> Result<(RlConfig, Option<(TrainState, Tensors)>), RlError> {
    match start {
        Start::Resume { total_steps, tasks, sample_recent } => {
            if !ckpt_path.exists() {
                return Err(RlError::NoCheckpoint { path: dir.to_path_buf() });
            }
            let (state, tensors) = read_checkpoint(ckpt_path)?;
            let mut c = state.config.clone();
            if let Some(t) = total_steps {
                if t < state.step {
                    return Err(RlError::Config(format!(
                        "the run already has {} steps; cannot shrink it to {t}",
                        state.step
                    )));
                }
                c.total_steps = t;
            }
            if let Some(t) = tasks {
                c.tasks = t.to_vec();
            }
            if let Some(w) = sample_recent {
                c.sample_recent = w;
            }
            Ok((c, Some((state, tensors))))
        }
        Start::New(c) => {
            if ckpt_path.exists() || dir.join("config.json").exists() {
                return Err(RlError::Exists { path: dir.to_path_buf() });
            }
            Ok((c.clone(), None))
        }
    }
}

/// The state and replay buffer of a resumed run, its weights and moments loaded into `agent`;
/// or a new run's (an empty buffer of the whole budget).
fn restore(
    loaded: Option<(TrainState, Tensors)>,
    agent: &mut Agent,
    cfg: &RlConfig,
    (in_dim, act_dim): (usize, usize),
    ckpt_path: &Path,
) -> Result<(TrainState, ReplayBuffer), RlError> {
    let capacity = cfg.total_steps as usize;
    let Some((state, tensors)) = loaded else {
        let state = TrainState {
            config: cfg.clone(),
            step: 0,
            episode: 0,
            updates: 0,
            episodes: vec![],
            snapshots: vec![],
            optimiser_steps: vec![],
            wall_seconds: 0.0,
        };
        return Ok((state, ReplayBuffer::new(in_dim, act_dim, capacity)));
    };
    let bad = |message: String| RlError::File { path: ckpt_path.to_path_buf(), message };
    let get = |n: &str| tensors.get(n).cloned();
    let steps: HashMap<String, u64> = state.optimiser_steps.iter().cloned().collect();
    agent.load_state(&get, &|n| steps.get(n).copied()).map_err(bad)?;
    let take =
        |n: &str| tensors.get(n).cloned().ok_or_else(|| bad(format!("missing tensor `{n}`")));
    let arrays = BufferArrays {
        obs: take("buffer.obs")?,
        actions: take("buffer.actions")?,
        rewards: take("buffer.rewards")?,
        next_obs: take("buffer.next_obs")?,
        terminated: take("buffer.terminated")?,
    };
    let capacity = capacity.max(state.step as usize);
    let buffer = ReplayBuffer::from_parts(in_dim, act_dim, capacity, arrays).map_err(bad)?;
    if buffer.len() as u64 != state.step {
        return Err(bad(format!(
            "buffer has {} transitions but the state says {} steps",
            buffer.len(),
            state.step
        )));
    }
    Ok((state, buffer))
}

fn push_recent(r: &mut VecDeque<f64>, v: f64) {
    if r.len() == 5 {
        r.pop_front();
    }
    r.push_back(v);
}

fn eval_specs(seed: u64, tasks: &[usize], episodes: usize) -> Vec<EpisodeSpec> {
    tasks
        .iter()
        .flat_map(|&task| {
            (0..episodes).map(move |e| {
                let mut rng =
                    stream_rng(seed, STREAM_EVAL, ((task as u64) << 32) ^ ((e as u64) << 48));
                let reset_seed = rng.random();
                EpisodeSpec { task, reset_seed, rng }
            })
        })
        .collect()
}

/// Mean return per task of `behaviour`, `episodes` per task.
fn evaluate(
    family: &dyn EnvFamily,
    behaviour: Behaviour<'_>,
    seed: u64,
    episodes: usize,
) -> Result<Vec<f64>, RlError> {
    let all: Vec<usize> = (0..family.num_tasks()).collect();
    evaluate_tasks(family, behaviour, seed, &all, episodes)
}

/// Mean return of `behaviour` on each of `tasks`, `episodes` per task. A task's evaluation
/// episodes (reset states) depend on the seed and the task only, so every policy evaluated on a
/// task meets the same episodes, whichever other tasks are evaluated with it.
pub(crate) fn evaluate_tasks(
    family: &dyn EnvFamily,
    behaviour: Behaviour<'_>,
    seed: u64,
    tasks: &[usize],
    episodes: usize,
) -> Result<Vec<f64>, RlError> {
    let trajs = run_episodes(
        family,
        behaviour,
        eval_specs(seed, tasks, episodes),
        512,
        // Threads for stepping evaluation episodes: the machine's cores.
        pdt_base::threads::available_cores(),
        &mut |_| {},
        &pdt_base::stop::StopFlag::default(),
    )?;
    Ok(trajs
        .chunks(episodes)
        .map(|c| c.iter().map(|t| t.episode_return()).sum::<f64>() / c.len() as f64)
        .collect())
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn snapshot(
    cfg: &RlConfig,
    family: &dyn EnvFamily,
    encoder: &TaskEncoder,
    agent: &Agent,
    step: u64,
    dir: &Path,
    device: Device,
) -> Result<SnapshotInfo, RlError> {
    let behaviour = Behaviour::Actor {
        actor: agent.actor(),
        head: agent.policy_head(),
        encoder,
        noise: Noise::Deterministic,
        device,
    };
    let eval_returns = evaluate(family, behaviour, cfg.seed, cfg.eval_episodes)?;
    let file = format!("actor-{step:09}.safetensors");
    let meta = policy_meta(cfg, encoder, agent, step, eval_returns.clone());
    policy::save(&dir.join("snapshots").join(&file), agent.actor(), &meta)?;
    Ok(SnapshotInfo { step, file, mean_return: mean(&eval_returns), eval_returns })
}

fn policy_meta(
    cfg: &RlConfig,
    encoder: &TaskEncoder,
    agent: &Agent,
    step: u64,
    eval_returns: Vec<f64>,
) -> PolicyMeta {
    PolicyMeta {
        format: POLICY_FORMAT.to_string(),
        algorithm: cfg.algorithm,
        family: cfg.family.clone(),
        sizes: agent.actor().sizes().to_vec(),
        act_dim: agent.act_dim(),
        head: agent.policy_head(),
        encoder: encoder.clone(),
        step,
        eval_returns,
    }
}

/// Picks the expert (the best-evaluated snapshot) and the medium policy (the snapshot whose mean
/// evaluation is closest to halfway between uniform random actions and the expert), copies them to
/// `dir/agent/` and writes `agent.json`.
fn finish(
    cfg: &RlConfig,
    family: &dyn EnvFamily,
    state: &TrainState,
    dir: &Path,
) -> Result<AgentCard, RlError> {
    let snaps = &state.snapshots;
    let expert = snaps
        .iter()
        .max_by(|a, b| a.mean_return.total_cmp(&b.mean_return).then(b.step.cmp(&a.step)))
        .ok_or_else(|| RlError::Config("training ended without a snapshot".into()))?;
    let random_eval = evaluate(family, Behaviour::Uniform, cfg.seed, cfg.eval_episodes)?;
    let half = 0.5 * (mean(&random_eval) + expert.mean_return);
    let medium = snaps
        .iter()
        .filter(|s| s.step < expert.step)
        .min_by(|a, b| (a.mean_return - half).abs().total_cmp(&(b.mean_return - half).abs()))
        .unwrap_or(expert);
    let agent_dir = dir.join("agent");
    std::fs::create_dir_all(&agent_dir)
        .map_err(|source| RlError::Io { path: agent_dir.clone(), source })?;
    for (name, s) in [("expert", expert), ("medium", medium)] {
        let bytes = std::fs::read(dir.join("snapshots").join(&s.file))
            .map_err(|source| RlError::Io { path: dir.join("snapshots").join(&s.file), source })?;
        write_atomic(&agent_dir.join(format!("{name}.safetensors")), &bytes)?;
    }
    let card = AgentCard {
        format: AGENT_CARD_FORMAT.to_string(),
        family: cfg.family.clone(),
        algorithm: cfg.algorithm,
        config: cfg.clone(),
        expert_step: expert.step,
        medium_step: medium.step,
        random_eval,
        medium_eval: medium.eval_returns.clone(),
        expert_eval: expert.eval_returns.clone(),
        snapshots: snaps.clone(),
        wall_seconds: state.wall_seconds,
        why_medium: format!(
            "the snapshot before the expert whose mean deterministic return is closest to {half:.2}, \
             halfway between uniform random actions and the expert"
        ),
        task_experts: vec![],
        dataset_noise: None,
    };
    let text = serde_json::to_string_pretty(&card).map_err(|e| RlError::Config(e.to_string()))?;
    write_atomic(&agent_dir.join("agent.json"), format!("{text}\n").as_bytes())?;
    Ok(card)
}

/// Reads `agent.json` of an agent directory.
pub fn read_agent_card(agent_dir: &Path) -> Result<AgentCard, RlError> {
    let path = agent_dir.join("agent.json");
    let text = pdt_base::fs::read_text_limited(&path, pdt_base::fs::MAX_TEXT_BYTES)
        .map_err(|source| RlError::Io { path: path.clone(), source })?;
    let card: AgentCard = serde_json::from_str(&text).map_err(|e| RlError::File {
        path: path.clone(),
        message: format!("invalid agent card: {e}"),
    })?;
    if card.format != AGENT_CARD_FORMAT {
        return Err(RlError::File {
            path,
            message: format!("format {:?}, expected {AGENT_CARD_FORMAT:?}", card.format),
        });
    }
    Ok(card)
}

fn write_episodes_csv(path: &Path, eps: &[EpisodeLog]) -> Result<(), RlError> {
    let mut s = String::from("episode,step,task,return,length\n");
    for e in eps {
        s.push_str(&format!(
            "{},{},{},{},{}\n",
            e.episode, e.step, e.task, e.episode_return, e.length
        ));
    }
    write_atomic(path, s.as_bytes())
}

fn write_checkpoint(
    path: &Path,
    state: &mut TrainState,
    agent: &Agent,
    buffer: &ReplayBuffer,
) -> Result<(), RlError> {
    let st = agent.state();
    let mut tensors = st.arrays;
    state.optimiser_steps = st.counters;
    tensors.push(("buffer.obs".into(), buffer.obs.clone()));
    tensors.push(("buffer.actions".into(), buffer.actions.clone()));
    tensors.push(("buffer.rewards".into(), buffer.rewards.clone()));
    tensors.push(("buffer.next_obs".into(), buffer.next_obs.clone()));
    tensors.push(("buffer.terminated".into(), buffer.terminated.clone()));
    let bad = |message: String| RlError::File { path: path.to_path_buf(), message };
    let bytes: Vec<(String, Vec<u8>, usize)> = tensors
        .iter()
        .map(|(n, v)| (n.clone(), v.iter().flat_map(|x| x.to_le_bytes()).collect(), v.len()))
        .collect();
    let views = bytes
        .iter()
        .map(|(n, b, len)| TensorView::new(Dtype::F32, vec![*len], b).map(|v| (n.clone(), v)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| bad(e.to_string()))?;
    let meta = serde_json::to_string(state).map_err(|e| bad(e.to_string()))?;
    let out = safetensors::serialize(views, &Some(HashMap::from([(STATE_KEY.to_string(), meta)])))
        .map_err(|e| bad(e.to_string()))?;
    write_atomic(path, &out)
}

type Tensors = HashMap<String, Vec<f32>>;

/// Reads a checkpoint: its state and every tensor, by name.
pub fn read_checkpoint(path: &Path) -> Result<(TrainState, Tensors), RlError> {
    let bad = |message: String| RlError::File { path: path.to_path_buf(), message };
    // The replay buffer is in the file (`total_steps` transitions of a few hundred bytes each), so
    // the bound is wider than for weights; the read still refuses FIFOs and devices.
    let bytes = pdt_base::fs::read_limited(path, 64 << 30)
        .map_err(|source| RlError::Io { path: path.to_path_buf(), source })?;
    let plain = |e: safetensors::SafeTensorError| {
        bad(format!("not a checkpoint: {}", describe_safetensors_error(&e, bytes.len())))
    };
    let (_, header) = SafeTensors::read_metadata(&bytes).map_err(plain)?;
    let meta =
        header.metadata().as_ref().and_then(|m| m.get(STATE_KEY)).ok_or_else(|| {
            bad(format!("no `{STATE_KEY}` metadata: not a promptdt RL checkpoint"))
        })?;
    let state: TrainState =
        serde_json::from_str(meta).map_err(|e| bad(format!("invalid state: {e}")))?;
    let st = SafeTensors::deserialize(&bytes).map_err(plain)?;
    let mut tensors = HashMap::new();
    for (name, view) in st.tensors() {
        if view.dtype() != Dtype::F32 {
            return Err(bad(format!("tensor `{name}` is {:?}, expected F32", view.dtype())));
        }
        let v: Vec<f32> = view
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        tensors.insert(name, v);
    }
    Ok((state, tensors))
}

/// `dir/agent`.
pub fn agent_dir(dir: &Path) -> PathBuf {
    dir.join("agent")
}
