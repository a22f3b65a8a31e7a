//! Soft Actor-Critic (Haarnoja et al. 2018, with the automatic temperature of the 2018b paper),
//! one flat module: a tanh-squashed Gaussian actor, twin critics with a Polyak-averaged target,
//! and a learned temperature alpha aiming at entropy `-act_dim`.
//!
//! All noise comes from the caller as standard normals, so an update is a pure function of
//! (state, batch, noise) and a resumed run repeats the same updates.

use crate::buffer::Batch;
use crate::nets::{grad_of, mlp_sizes, Adam, Mlp};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

/// SAC hyper-parameters (defaults: the SAC paper's / Stable-Baselines3's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SacConfig {
    pub hidden: Vec<i64>,
    pub actor_lr: f64,
    pub critic_lr: f64,
    pub alpha_lr: f64,
    pub gamma: f64,
    pub tau: f64,
    /// Initial temperature.
    pub init_alpha: f64,
}

impl Default for SacConfig {
    fn default() -> Self {
        Self {
            hidden: vec![256, 256],
            actor_lr: 3e-4,
            critic_lr: 3e-4,
            alpha_lr: 3e-4,
            gamma: 0.99,
            tau: 0.005,
            init_alpha: 1.0,
        }
    }
}

/// log std is clamped to this range (as Stable-Baselines3) so exp() neither vanishes nor explodes.
const LOG_STD_MIN: f64 = -20.0;
const LOG_STD_MAX: f64 = 2.0;
const HALF_LOG_2PI: f64 = 0.918_938_533_204_672_7;

/// Diagnostics of one update.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SacStats {
    pub critic_loss: f64,
    pub actor_loss: f64,
    pub alpha: f64,
}

#[derive(Debug)]
pub struct Sac {
    pub cfg: SacConfig,
    pub obs_dim: i64,
    pub act_dim: i64,
    /// `obs -> [mean, log_std]`, `[D, h.., 2A]`.
    pub actor: Mlp,
    /// Twin critics `[obs, act] -> Q`, an ensemble of 2.
    pub critic: Mlp,
    pub critic_target: Mlp,
    /// `[1]`, a leaf.
    pub log_alpha: Tensor,
    pub actor_opt: Adam,
    pub critic_opt: Adam,
    pub alpha_opt: Adam,
}

impl Sac {
    pub fn new(
        obs_dim: i64,
        act_dim: i64,
        cfg: SacConfig,
        rng: &mut ChaCha8Rng,
        device: Device,
    ) -> Self {
        let actor = Mlp::new(&mlp_sizes(obs_dim, &cfg.hidden, 2 * act_dim), 1, rng, device);
        let critic = Mlp::new(&mlp_sizes(obs_dim + act_dim, &cfg.hidden, 1), 2, rng, device);
        let critic_target = critic.detached_copy();
        let log_alpha = Tensor::from_slice(&[cfg.init_alpha.ln() as f32])
            .to_device(device)
            .set_requires_grad(true);
        let actor_opt = Adam::new(&actor.flat, cfg.actor_lr);
        let critic_opt = Adam::new(&critic.flat, cfg.critic_lr);
        let alpha_opt = Adam::new(&log_alpha, cfg.alpha_lr);
        Self {
            cfg,
            obs_dim,
            act_dim,
            actor,
            critic,
            critic_target,
            log_alpha,
            actor_opt,
            critic_opt,
            alpha_opt,
        }
    }

    /// `(mean, log_std)`, each `[B, A]`.
    pub fn actor_head(actor: &Mlp, act_dim: i64, obs: &Tensor) -> (Tensor, Tensor) {
        let out = actor.forward(obs).squeeze_dim(0); // [B, 2A]
        let mean = out.narrow(1, 0, act_dim);
        let log_std = out.narrow(1, act_dim, act_dim).clamp(LOG_STD_MIN, LOG_STD_MAX);
        (mean, log_std)
    }

    /// A reparameterised sample `tanh(mean + std * noise)` and its log-probability `[B, 1]`
    /// (Gaussian log-density minus the tanh Jacobian, in the stable form
    /// `log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u))`).
    fn sample(&self, obs: &Tensor, noise: &Tensor) -> (Tensor, Tensor) {
        let (mean, log_std) = Self::actor_head(&self.actor, self.act_dim, obs);
        let u = &mean + log_std.exp() * noise; // [B, A]
        let action = u.tanh();
        let gauss =
            (noise.square() * -0.5 - &log_std - HALF_LOG_2PI).sum_dim_intlist(1, true, Kind::Float);
        let jac = ((-&u * 2.0).softplus() + &u - std::f64::consts::LN_2) * 2.0; // -log(1 - tanh^2)
        let log_prob = gauss + jac.sum_dim_intlist(1, true, Kind::Float); // [B, 1]
        (action, log_prob)
    }

    /// Actions for a batch of observations `[N, D]`: `tanh(mean + std * noise)`, or `tanh(mean)`
    /// when `noise` is `None` (the deterministic evaluation policy).
    pub fn act(&self, obs: &Tensor, noise: Option<&Tensor>) -> Tensor {
        tch::no_grad(|| {
            let (mean, log_std) = Self::actor_head(&self.actor, self.act_dim, obs);
            match noise {
                Some(n) => (mean + log_std.exp() * n).tanh(),
                None => mean.tanh(),
            }
        })
    }

    /// One gradient step of critics, actor and temperature, then the target update.
    /// `noise_next` and `noise_pi` are `[B, A]` standard normals.
    pub fn update(&mut self, b: &Batch, noise_next: &Tensor, noise_pi: &Tensor) -> SacStats {
        let alpha = self.log_alpha.detach().exp(); // [1]
        let target = tch::no_grad(|| {
            let (next_a, next_logp) = self.sample(&b.next_obs, noise_next);
            let q_next = self.critic_target.forward(&Tensor::cat(&[&b.next_obs, &next_a], 1)); // [2, B, 1]
            let q_next = q_next.amin(0, false) - &alpha * next_logp; // [B, 1]
            &b.rewards + &b.not_done * q_next * self.cfg.gamma
        });
        let q = self.critic.forward(&Tensor::cat(&[&b.obs, &b.actions], 1)); // [2, B, 1]

        // Sum of the two critics' MSE losses.
        let critic_loss = (q - target.unsqueeze(0))
            .square()
            .mean_dim(&[1i64, 2][..], false, Kind::Float)
            .sum(Kind::Float);
        let g = grad_of(&critic_loss, &self.critic.flat);
        self.critic_opt.update(&mut self.critic.flat, &g);

        let (a, logp) = self.sample(&b.obs, noise_pi);
        let q_pi = self.critic.forward(&Tensor::cat(&[&b.obs, &a], 1)).amin(0, false); // [B, 1]
        let actor_loss = (&alpha * &logp - q_pi).mean(Kind::Float);
        let g = grad_of(&actor_loss, &self.actor.flat);
        self.actor_opt.update(&mut self.actor.flat, &g);

        let target_entropy = -(self.act_dim as f64);
        let alpha_loss = -(&self.log_alpha * (logp.detach() + target_entropy)).mean(Kind::Float);
        let g = grad_of(&alpha_loss, &self.log_alpha);
        self.alpha_opt.update(&mut self.log_alpha, &g);

        self.critic.soft_update_into(&mut self.critic_target, self.cfg.tau);
        SacStats {
            critic_loss: critic_loss.double_value(&[]),
            actor_loss: actor_loss.double_value(&[]),
            alpha: alpha.double_value(&[0]),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn log_prob_matches_a_direct_formula() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let sac = Sac::new(
            3,
            2,
            SacConfig { hidden: vec![8], ..Default::default() },
            &mut rng,
            Device::Cpu,
        );
        let obs = Tensor::from_slice(&[0.3f32, -1.0, 0.5, 0.1, 0.2, 0.9]).view([2, 3]);
        let noise = Tensor::from_slice(&[0.5f32, -1.5, 0.0, 2.0]).view([2, 2]);
        let (a, lp) = sac.sample(&obs, &noise);
        let (mean, log_std) = Sac::actor_head(&sac.actor, 2, &obs);
        let u = &mean + log_std.exp() * &noise;
        // log N(u; mean, std) - sum log(1 - tanh(u)^2)
        let direct = ((&u - &mean).square() / (log_std.exp().square() * 2.0) * -1.0
            - &log_std
            - HALF_LOG_2PI
            - (-u.tanh().square() + 1.0).log())
        .sum_dim_intlist(1, true, Kind::Float);
        let diff = (lp - direct).abs().max().double_value(&[]);
        assert!(diff < 1e-4, "{diff}");
        assert!(a.abs().max().double_value(&[]) < 1.0);
    }
}
