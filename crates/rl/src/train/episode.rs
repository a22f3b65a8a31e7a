//! One training episode of [`super::train`]: a task drawn from the episode's stream, then steps
//! until the episode ends (or the budget does), each an action (uniform at first, then the actor's
//! with exploration noise), a transition into the buffer and `updates_per_step` updates.

use super::{RlConfig, TrainState, STREAM_ACT, STREAM_BATCH, STREAM_EPISODE};
use crate::agent::{actor_raw, Agent, Noise, TaskEncoder, UpdateStats};
use crate::buffer::{ReplayBuffer, Transition};
use crate::{stream_rng, RlError};
use pdt_envs::{Env, EnvFamily};
use rand::Rng;
use tch::Device;

/// What an episode reads and does not change.
pub(super) struct World<'a> {
    pub cfg: &'a RlConfig,
    pub family: &'a dyn EnvFamily,
    pub encoder: &'a TaskEncoder,
    /// The tasks trained on.
    pub tasks: &'a [usize],
    pub act_dim: usize,
    pub device: Device,
}

/// What an episode changes: the learner, its buffer and state, and the environments made so far
/// (one per task, made on first use) with the scratch vectors reused from step to step.
pub(super) struct Learning {
    pub agent: Agent,
    pub buffer: ReplayBuffer,
    pub state: TrainState,
    pub last_update: UpdateStats,
    pub envs: Vec<Option<Box<dyn Env>>>,
    pub x: Vec<f32>,
    pub x_next: Vec<f32>,
    pub action: Vec<f32>,
}

/// One finished episode: its task, return and length.
pub(super) struct Played {
    pub task: usize,
    pub ret: f64,
    pub len: usize,
}

impl Learning {
    /// Plays one episode, learning as it goes; stops early with an error where the environment or
    /// the critic diverges (a non-finite value).
    pub fn episode(&mut self, w: &World<'_>) -> Result<Played, RlError> {
        let cfg = w.cfg;
        let head = self.agent.policy_head();
        let mut erng = stream_rng(cfg.seed, STREAM_EPISODE, self.state.episode);
        let task = w.tasks[erng.random_range(0..w.tasks.len())];
        let reset_seed: u64 = erng.random();
        let env = match &mut self.envs[task] {
            Some(e) => e,
            slot => slot.insert(w.family.make(task)?),
        };
        let obs = env.reset(reset_seed);
        self.x.clear();
        w.encoder.encode(&obs, task, &mut self.x);
        let (mut ret, mut len) = (0.0f64, 0usize);
        let state = &mut self.state;
        loop {
            let mut arng = stream_rng(cfg.seed, STREAM_ACT, state.step);
            self.action.clear();
            if state.step < cfg.learning_starts {
                for _ in 0..w.act_dim {
                    self.action.push(arng.random_range(-1.0f32..=1.0));
                }
            } else {
                let raw = actor_raw(self.agent.actor(), &self.x, 1, w.device);
                head.action(&raw, w.act_dim, Noise::Explore, &mut arng, &mut self.action);
            }
            let step = env.step(&self.action)?;
            if !step.reward.is_finite() || step.obs.iter().any(|v| !v.is_finite()) {
                return Err(RlError::Diverged(format!(
                    "{} task {task}: non-finite observation or reward at step {}",
                    cfg.family, state.step
                )));
            }
            self.x_next.clear();
            w.encoder.encode(&step.obs, task, &mut self.x_next);
            self.buffer.push(Transition {
                obs: &self.x,
                action: &self.action,
                reward: step.reward,
                next_obs: &self.x_next,
                terminated: step.terminated,
            });
            state.step += 1;
            ret += step.reward as f64;
            len += 1;
            if state.step >= cfg.learning_starts {
                for _ in 0..cfg.updates_per_step {
                    let mut brng = stream_rng(cfg.seed, STREAM_BATCH, state.updates);
                    let recent = cfg.sample_recent as usize;
                    let batch =
                        self.buffer.sample_recent(cfg.batch_size, recent, &mut brng, w.device);
                    self.last_update = self.agent.update(&batch, &mut brng);
                    state.updates += 1;
                }
                if !self.last_update.critic_loss.is_finite() {
                    return Err(RlError::Diverged(format!(
                        "critic loss {} at step {}",
                        self.last_update.critic_loss, state.step
                    )));
                }
            }
            std::mem::swap(&mut self.x, &mut self.x_next);
            if step.terminated || step.truncated || state.step >= cfg.total_steps {
                return Ok(Played { task, ret, len });
            }
        }
    }
}
