//! Many episodes at once: every unfinished episode of a chunk is stepped together, with one
//! batched actor forward per environment step. Each episode draws its reset seed and its action
//! noise from its own generator, so an episode does not depend on which others share its chunk.

use crate::agent::{actor_raw, Noise, PolicyHead, TaskEncoder};
use crate::nets::Mlp;
use crate::RlError;
use pdt_base::stop::StopFlag;
use pdt_data::Trajectory;
use pdt_envs::rollout::{run_batch, BatchPolicy};
use pdt_envs::vec_env::VecEnv;
use pdt_envs::{EnvError, EnvFamily, StepResult};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use tch::Device;

/// One episode to run.
#[derive(Debug, Clone)]
pub struct EpisodeSpec {
    pub task: usize,
    pub reset_seed: u64,
    /// Source of the episode's action noise.
    pub rng: ChaCha8Rng,
}

/// Who acts.
#[derive(Debug, Clone, Copy)]
pub enum Behaviour<'a> {
    Actor {
        actor: &'a Mlp,
        head: PolicyHead,
        encoder: &'a TaskEncoder,
        noise: Noise,
        device: Device,
    },
    /// Uniform random actions in [-1, 1] (the first episodes of a replay buffer).
    Uniform,
}

struct Running {
    spec: EpisodeSpec,
    obs: Vec<f32>,
    observations: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    terminated: Vec<bool>,
    truncated: Vec<bool>,
}

/// One chunk of episodes as the [`run_batch`] loop drives it (slot `i` is `running[i]`).
struct Chunk<'b> {
    behaviour: Behaviour<'b>,
    act_dim: usize,
    running: Vec<Running>,
    /// The actor's input rows, reused across steps.
    inputs: Vec<f32>,
    /// Checked before every step of the chunk (a chunk of MuJoCo episodes takes seconds).
    interrupt: &'b StopFlag,
}

impl BatchPolicy for Chunk<'_> {
    type Error = RlError;

    fn act(&mut self, slots: &[usize]) -> Result<Vec<f32>, RlError> {
        if self.interrupt.is_set() {
            return Err(RlError::Interrupted);
        }
        let act_dim = self.act_dim;
        let raw = match self.behaviour {
            Behaviour::Actor { actor, encoder, device, .. } => {
                self.inputs.clear();
                for &i in slots {
                    encoder.encode(
                        &self.running[i].obs,
                        self.running[i].spec.task,
                        &mut self.inputs,
                    );
                }
                actor_raw(actor, &self.inputs, slots.len(), device)
            }
            Behaviour::Uniform => Vec::new(),
        };
        let mut out = Vec::with_capacity(slots.len() * act_dim);
        let mut action = Vec::with_capacity(act_dim);
        for (k, &i) in slots.iter().enumerate() {
            let ep = &mut self.running[i];
            action.clear();
            match self.behaviour {
                Behaviour::Actor { head, noise, encoder, .. } => {
                    let w = head.raw_dim(act_dim);
                    head.action(
                        &raw[k * w..(k + 1) * w],
                        act_dim,
                        noise,
                        &mut ep.spec.rng,
                        &mut action,
                    );
                    encoder.decode_action(&mut action);
                }
                Behaviour::Uniform => {
                    for _ in 0..act_dim {
                        action.push(ep.spec.rng.random_range(-1.0f32..=1.0));
                    }
                }
            }
            ep.actions.extend_from_slice(&action);
            out.extend_from_slice(&action);
        }
        Ok(out)
    }

    fn batch_error(&self, _slots: &[usize], error: EnvError) -> RlError {
        error.into()
    }

    fn record(
        &mut self,
        slot: usize,
        _action: &[f32],
        step: Result<StepResult, EnvError>,
    ) -> Result<bool, RlError> {
        let step = step?;
        let ep = &mut self.running[slot];
        ep.observations.extend_from_slice(&ep.obs);
        ep.rewards.push(step.reward);
        ep.terminated.push(step.terminated);
        ep.truncated.push(step.truncated);
        ep.obs = step.obs;
        Ok(step.terminated || step.truncated)
    }
}

/// Runs `specs` in chunks of `chunk` episodes, stepping each chunk's environments on `threads`
/// threads (a [`VecEnv`]); returns the trajectories in spec order. `progress(done)` is called with
/// the number of finished episodes after each chunk. A stop asked for through `interrupt` ends it
/// with [`RlError::Interrupted`] before the next step.
///
/// The result depends on the specs and `chunk` only: not on `threads` (environments are
/// independent), but `chunk` sets the actor's batch sizes, and a batched matmul may round the
/// last bit differently for different batch sizes.
pub fn run_episodes(
    family: &dyn EnvFamily,
    behaviour: Behaviour<'_>,
    specs: Vec<EpisodeSpec>,
    chunk: usize,
    threads: usize,
    progress: &mut dyn FnMut(usize),
    interrupt: &StopFlag,
) -> Result<Vec<Trajectory>, RlError> {
    let preset = family.preset();
    let (obs_dim, act_dim) = (preset.obs_dim, preset.act_dim);
    let mut out = Vec::with_capacity(specs.len());
    let mut specs = specs.into_iter().peekable();
    while specs.peek().is_some() {
        let mut running = Vec::with_capacity(chunk);
        let mut envs = Vec::with_capacity(chunk);
        for spec in specs.by_ref().take(chunk.max(1)) {
            let env = family.make(spec.task)?;
            let h = env.horizon();
            envs.push(env);
            running.push(Running {
                spec,
                obs: Vec::new(),
                observations: Vec::with_capacity(h * obs_dim),
                actions: Vec::with_capacity(h * act_dim),
                rewards: Vec::with_capacity(h),
                terminated: Vec::with_capacity(h),
                truncated: Vec::with_capacity(h),
            });
        }
        let mut venv = VecEnv::new(envs, threads);
        let seeds: Vec<u64> = running.iter().map(|r| r.spec.reset_seed).collect();
        for (r, obs) in running.iter_mut().zip(venv.reset(&seeds)?) {
            r.obs = obs;
        }
        let slots = (0..running.len()).collect();
        let mut chunk = Chunk { behaviour, act_dim, running, inputs: Vec::new(), interrupt };
        run_batch(&mut venv, slots, &mut chunk)?;
        let running = chunk.running;
        for ep in running {
            let traj = Trajectory::new(
                obs_dim,
                act_dim,
                ep.observations,
                ep.actions,
                ep.rewards,
                ep.terminated,
                ep.truncated,
            )
            .map_err(|e| RlError::Config(format!("rollout produced an invalid trajectory: {e}")))?;
            out.push(traj);
        }
        progress(out.len());
    }
    Ok(out)
}
