//! Twin Delayed DDPG (Fujimoto et al. 2018), one flat module: a deterministic tanh actor with a
//! target copy, twin critics with a target copy, target-policy smoothing, delayed actor updates.
//!
//! As in `sac.rs`, every random number arrives from the caller, so updates are reproducible.

use crate::buffer::Batch;
use crate::nets::{grad_of, mlp_sizes, Adam, Mlp};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

/// TD3 hyper-parameters (defaults: the TD3 paper's, with its author's 256-unit networks).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Td3Config {
    pub hidden: Vec<i64>,
    pub actor_lr: f64,
    pub critic_lr: f64,
    pub gamma: f64,
    pub tau: f64,
    /// Std of the target-policy smoothing noise, and its clip.
    pub policy_noise: f64,
    pub noise_clip: f64,
    /// The actor and the targets are updated every `policy_delay` critic updates.
    pub policy_delay: u64,
    /// Std of the Gaussian exploration noise added to actions while collecting.
    pub exploration_noise: f64,
}

impl Default for Td3Config {
    fn default() -> Self {
        Self {
            hidden: vec![256, 256],
            actor_lr: 3e-4,
            critic_lr: 3e-4,
            gamma: 0.99,
            tau: 0.005,
            policy_noise: 0.2,
            noise_clip: 0.5,
            policy_delay: 2,
            exploration_noise: 0.1,
        }
    }
}

/// Diagnostics of one update (`actor_loss` is that of the last actor update).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Td3Stats {
    pub critic_loss: f64,
    pub actor_loss: f64,
}

#[derive(Debug)]
pub struct Td3 {
    pub cfg: Td3Config,
    pub obs_dim: i64,
    pub act_dim: i64,
    pub actor: Mlp,
    pub actor_target: Mlp,
    pub critic: Mlp,
    pub critic_target: Mlp,
    pub actor_opt: Adam,
    pub critic_opt: Adam,
    /// Critic updates done so far (the actor's delay counts them).
    pub updates: u64,
    last_actor_loss: f64,
}

impl Td3 {
    pub fn new(
        obs_dim: i64,
        act_dim: i64,
        cfg: Td3Config,
        rng: &mut ChaCha8Rng,
        device: Device,
    ) -> Self {
        let actor = Mlp::new(&mlp_sizes(obs_dim, &cfg.hidden, act_dim), 1, rng, device);
        let critic = Mlp::new(&mlp_sizes(obs_dim + act_dim, &cfg.hidden, 1), 2, rng, device);
        let actor_target = actor.detached_copy();
        let critic_target = critic.detached_copy();
        let actor_opt = Adam::new(&actor.flat, cfg.actor_lr);
        let critic_opt = Adam::new(&critic.flat, cfg.critic_lr);
        Self {
            cfg,
            obs_dim,
            act_dim,
            actor,
            actor_target,
            critic,
            critic_target,
            actor_opt,
            critic_opt,
            updates: 0,
            last_actor_loss: 0.0,
        }
    }

    fn policy(actor: &Mlp, obs: &Tensor) -> Tensor {
        actor.forward(obs).squeeze_dim(0).tanh() // [B, A]
    }

    /// `clip(tanh(actor(obs)) + std * noise, -1, 1)`; without noise the deterministic policy.
    pub fn act(&self, obs: &Tensor, noise: Option<&Tensor>, std: f64) -> Tensor {
        tch::no_grad(|| {
            let a = Self::policy(&self.actor, obs);
            match noise {
                Some(n) => (a + n * std).clamp(-1.0, 1.0),
                None => a,
            }
        })
    }

    /// One critic update (and, every `policy_delay`, an actor + target update). `noise` is
    /// `[B, A]` standard normals for the target-policy smoothing.
    pub fn update(&mut self, b: &Batch, noise: &Tensor) -> Td3Stats {
        let c = &self.cfg;
        let target = tch::no_grad(|| {
            let smooth = (noise * c.policy_noise).clamp(-c.noise_clip, c.noise_clip);
            let next_a = (Self::policy(&self.actor_target, &b.next_obs) + smooth).clamp(-1.0, 1.0);
            let q_next =
                self.critic_target.forward(&Tensor::cat(&[&b.next_obs, &next_a], 1)).amin(0, false); // [B, 1]
            &b.rewards + &b.not_done * q_next * c.gamma
        });
        let q = self.critic.forward(&Tensor::cat(&[&b.obs, &b.actions], 1)); // [2, B, 1]
        let critic_loss = (q - target.unsqueeze(0))
            .square()
            .mean_dim(&[1i64, 2][..], false, Kind::Float)
            .sum(Kind::Float);
        let g = grad_of(&critic_loss, &self.critic.flat);
        self.critic_opt.update(&mut self.critic.flat, &g);
        self.updates += 1;

        if self.updates.is_multiple_of(self.cfg.policy_delay.max(1)) {
            let a = Self::policy(&self.actor, &b.obs);
            // The actor follows the first critic only, as in TD3.
            let q1 = self.critic.forward(&Tensor::cat(&[&b.obs, &a], 1)).get(0); // [B, 1]
            let actor_loss = -q1.mean(Kind::Float);
            let g = grad_of(&actor_loss, &self.actor.flat);
            self.actor_opt.update(&mut self.actor.flat, &g);
            self.last_actor_loss = actor_loss.double_value(&[]);
            self.actor.soft_update_into(&mut self.actor_target, self.cfg.tau);
            self.critic.soft_update_into(&mut self.critic_target, self.cfg.tau);
        }
        Td3Stats { critic_loss: critic_loss.double_value(&[]), actor_loss: self.last_actor_loss }
    }
}
