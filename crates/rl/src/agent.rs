//! What SAC and TD3 share: the task-conditioned input, the agent behind one enum, the exported
//! policy (actor only) and the host-side action noise.
//!
//! **Task conditioning.** One agent serves every task of a family: its networks see the
//! environment's observation plus the task parameter (direction, target velocity, goal angle as
//! (cos, sin)). Datasets store the environment's observation only, as the reference data does.
//! For HalfCheetah the agent also does not see `obs[17]`, the torso's absolute x position (it grows
//! without bound, which gym's own HalfCheetah leaves out of the observation for the same reason);
//! the datasets keep it.

use crate::nets::{tensor_to_vec, Mlp};
use crate::sac::{Sac, SacConfig};
use crate::td3::{Td3, Td3Config};
use crate::RlError;
use pdt_envs::EnvFamily;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Device, Tensor};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Algorithm {
    Sac,
    Td3,
}

impl Algorithm {
    pub fn name(self) -> &'static str {
        match self {
            Algorithm::Sac => "sac",
            Algorithm::Td3 => "td3",
        }
    }
}

impl std::str::FromStr for Algorithm {
    type Err = RlError;
    fn from_str(s: &str) -> Result<Self, RlError> {
        match s {
            "sac" => Ok(Algorithm::Sac),
            "td3" => Ok(Algorithm::Td3),
            other => Err(RlError::Config(format!("unknown algorithm `{other}` (known: sac, td3)"))),
        }
    }
}

/// A family's RL preset: `configs/collect/<family>.toml`, which the family hands over as text
/// ([`EnvFamily::rl_preset`]), so that a new family needs no edit in this crate.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CollectPreset {
    pub algorithm: Algorithm,
    /// Environment steps in all.
    pub total_steps: u64,
    /// Observation indices the agent does not see.
    #[serde(default)]
    pub drop_obs: Vec<usize>,
}

impl CollectPreset {
    /// The preset of `family`; an error names a family without one, or a malformed file.
    pub fn of(family: &dyn EnvFamily) -> Result<Self, RlError> {
        let name = family.name();
        let text = family
            .rl_preset()
            .ok_or_else(|| RlError::Config(format!("no RL preset for family `{name}`")))?;
        toml::from_str(text)
            .map_err(|e| RlError::Config(format!("configs/collect/{name}.toml: {e}")))
    }
}

/// The agent's input for a family: which observation entries it drops and the per-task features
/// it appends.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskEncoder {
    pub family: String,
    pub obs_dim: usize,
    /// Observation indices the agent does not see.
    pub drop: Vec<usize>,
    /// `task_features[task]`, all of the same length.
    pub task_features: Vec<Vec<f32>>,
    /// Set on a mirrored policy (see [`Mirror`]); never while training.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mirror: Option<Mirror>,
}

/// A symmetry of the body used to act in a mirrored world: the actor sees the mirrored observation
/// and the mirrored task feature, and its action is mirrored back. With it an agent that walks
/// well towards some directions also walks towards their mirror images (Ant-Dir; the maps come
/// from `pdt_envs::ant_dir::Symmetry`, whose test steps mirrored states). Each map is a signed
/// permutation `out[i] = sign[i] * x[index[i]]` and its own inverse (a reflection or a half turn).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Mirror {
    pub name: String,
    pub obs_index: Vec<usize>,
    pub obs_sign: Vec<f32>,
    pub action_index: Vec<usize>,
    pub action_sign: Vec<f32>,
    pub task_feature_sign: Vec<f32>,
}

impl Mirror {
    /// The family's mirror symmetries ([`EnvFamily::symmetries`]; none for the HalfCheetah
    /// families: a mirror image of running forward is not running in another direction they
    /// have), none for an unknown family.
    pub fn for_family(family: &str) -> Vec<Mirror> {
        let Ok(family) = pdt_envs::family(family) else {
            return vec![];
        };
        let f32s = |v: Vec<f64>| v.into_iter().map(|x| x as f32).collect::<Vec<f32>>();
        family
            .symmetries()
            .into_iter()
            .map(|r| Mirror {
                name: r.name.to_string(),
                obs_index: r.observation.index,
                obs_sign: f32s(r.observation.sign),
                action_index: r.action.index,
                action_sign: f32s(r.action.sign),
                task_feature_sign: f32s(r.task_feature_sign),
            })
            .collect()
    }

    /// Whether the maps fit an observation, action and task feature of these sizes.
    pub fn fits(&self, obs_dim: usize, act_dim: usize, feature_dim: usize) -> bool {
        let ok = |index: &[usize], sign: &[f32], n: usize| {
            index.len() == n && sign.len() == n && index.iter().all(|&i| i < n)
        };
        ok(&self.obs_index, &self.obs_sign, obs_dim)
            && ok(&self.action_index, &self.action_sign, act_dim)
            && self.task_feature_sign.len() == feature_dim
    }
}

impl TaskEncoder {
    pub fn for_family(family: &dyn EnvFamily) -> Result<Self, RlError> {
        let name = family.name().to_string();
        let preset = family.preset();
        let task_features = (0..family.num_tasks())
            .map(|task| family.task_features(task))
            .collect::<Result<Vec<_>, _>>()?;
        let drop = CollectPreset::of(family)?.drop_obs;
        Ok(Self { family: name, obs_dim: preset.obs_dim, drop, task_features, mirror: None })
    }

    /// Length of the agent's input.
    pub fn input_dim(&self) -> usize {
        self.obs_dim - self.drop.len() + self.task_features.first().map_or(0, Vec::len)
    }

    /// Appends the agent's input for `obs` of `task` to `out`.
    pub fn encode(&self, obs: &[f32], task: usize, out: &mut Vec<f32>) {
        let seen = |i: usize| match &self.mirror {
            Some(m) => m.obs_sign[i] * obs[m.obs_index[i]],
            None => obs[i],
        };
        for i in 0..obs.len() {
            if !self.drop.contains(&i) {
                out.push(seen(i));
            }
        }
        if let Some(f) = self.task_features.get(task) {
            match &self.mirror {
                Some(m) => out.extend(f.iter().zip(&m.task_feature_sign).map(|(v, s)| v * s)),
                None => out.extend_from_slice(f),
            }
        }
    }

    /// Turns the actor's action into the environment's (mirrors it back; a no-op unmirrored).
    pub fn decode_action(&self, action: &mut [f32]) {
        if let Some(m) = &self.mirror {
            let a = action.to_vec();
            for (i, v) in action.iter_mut().enumerate() {
                *v = m.action_sign[i] * a[m.action_index[i]];
            }
        }
    }
}

/// Hyper-parameters of both algorithms (only the chosen one's are used).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct AgentConfig {
    pub sac: SacConfig,
    pub td3: Td3Config,
}

/// A learning agent.
#[derive(Debug)]
pub enum Agent {
    Sac(Sac),
    Td3(Td3),
}

/// A batch of standard normals from `rng` (Box-Muller, both outputs of each pair used:
/// [`pdt_base::random::standard_normals_f32`]).
pub fn normals(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
    pdt_base::random::standard_normals_f32(|| rng.random::<f64>(), n)
}

fn normal_tensor(rng: &mut ChaCha8Rng, rows: i64, cols: i64, device: Device) -> Tensor {
    Tensor::from_slice(&normals(rng, (rows * cols) as usize)).view([rows, cols]).to_device(device)
}

/// Losses of one update, for progress display.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UpdateStats {
    pub critic_loss: f64,
    pub actor_loss: f64,
}

impl Agent {
    pub fn new(
        algorithm: Algorithm,
        obs_dim: usize,
        act_dim: usize,
        cfg: &AgentConfig,
        rng: &mut ChaCha8Rng,
        device: Device,
    ) -> Self {
        let (d, a) = (obs_dim as i64, act_dim as i64);
        match algorithm {
            Algorithm::Sac => Agent::Sac(Sac::new(d, a, cfg.sac.clone(), rng, device)),
            Algorithm::Td3 => Agent::Td3(Td3::new(d, a, cfg.td3.clone(), rng, device)),
        }
    }

    pub fn algorithm(&self) -> Algorithm {
        match self {
            Agent::Sac(_) => Algorithm::Sac,
            Agent::Td3(_) => Algorithm::Td3,
        }
    }

    pub fn act_dim(&self) -> usize {
        match self {
            Agent::Sac(s) => s.act_dim as usize,
            Agent::Td3(t) => t.act_dim as usize,
        }
    }

    pub fn actor(&self) -> &Mlp {
        match self {
            Agent::Sac(s) => &s.actor,
            Agent::Td3(t) => &t.actor,
        }
    }

    /// The exploring policy's noise scale (TD3) — SAC's comes from its own std.
    pub fn policy_head(&self) -> PolicyHead {
        match self {
            Agent::Sac(_) => PolicyHead::Sac,
            Agent::Td3(t) => PolicyHead::Td3 { exploration_noise: t.cfg.exploration_noise as f32 },
        }
    }

    /// One update on a batch, with its noise drawn from `rng`.
    pub fn update(&mut self, batch: &crate::buffer::Batch, rng: &mut ChaCha8Rng) -> UpdateStats {
        let b = batch.obs.size()[0];
        let dev = batch.obs.device();
        match self {
            Agent::Sac(s) => {
                let n1 = normal_tensor(rng, b, s.act_dim, dev);
                let n2 = normal_tensor(rng, b, s.act_dim, dev);
                let st = s.update(batch, &n1, &n2);
                UpdateStats { critic_loss: st.critic_loss, actor_loss: st.actor_loss }
            }
            Agent::Td3(t) => {
                let n = normal_tensor(rng, b, t.act_dim, dev);
                let st = t.update(batch, &n);
                UpdateStats { critic_loss: st.critic_loss, actor_loss: st.actor_loss }
            }
        }
    }

    /// Every tensor of the agent (networks, targets, optimiser moments) as named host arrays,
    /// plus the optimiser step counts, for checkpoints.
    pub fn state(&self) -> AgentState {
        let mut t: Vec<(String, Vec<f32>)> = Vec::new();
        let mut steps = Vec::new();
        let mut opt = |name: &str, o: &crate::nets::Adam, t: &mut Vec<(String, Vec<f32>)>| {
            let (m, v) = o.state_vecs();
            t.push((format!("{name}_opt.exp_avg"), m));
            t.push((format!("{name}_opt.exp_avg_sq"), v));
            steps.push((format!("{name}_opt"), o.step));
        };
        match self {
            Agent::Sac(s) => {
                t.push(("actor".into(), s.actor.to_vec()));
                t.push(("critic".into(), s.critic.to_vec()));
                t.push(("critic_target".into(), s.critic_target.to_vec()));
                t.push(("log_alpha".into(), tensor_to_vec(&s.log_alpha)));
                opt("actor", &s.actor_opt, &mut t);
                opt("critic", &s.critic_opt, &mut t);
                opt("alpha", &s.alpha_opt, &mut t);
            }
            Agent::Td3(d) => {
                t.push(("actor".into(), d.actor.to_vec()));
                t.push(("actor_target".into(), d.actor_target.to_vec()));
                t.push(("critic".into(), d.critic.to_vec()));
                t.push(("critic_target".into(), d.critic_target.to_vec()));
                opt("actor", &d.actor_opt, &mut t);
                opt("critic", &d.critic_opt, &mut t);
                steps.push(("updates".into(), d.updates));
            }
        }
        AgentState { arrays: t, counters: steps }
    }

    /// Restores what [`Agent::state`] saved.
    pub fn load_state(
        &mut self,
        get: &dyn Fn(&str) -> Option<Vec<f32>>,
        steps: &dyn Fn(&str) -> Option<u64>,
    ) -> Result<(), String> {
        let need = |name: &str| get(name).ok_or_else(|| format!("missing tensor `{name}`"));
        let need_step = |name: &str| steps(name).ok_or_else(|| format!("missing counter `{name}`"));
        let load_opt = |name: &str, o: &mut crate::nets::Adam| -> Result<(), String> {
            let m = need(&format!("{name}_opt.exp_avg"))?;
            let v = need(&format!("{name}_opt.exp_avg_sq"))?;
            o.load_state(need_step(&format!("{name}_opt"))?, &m, &v)
                .map_err(|e| format!("{name}_opt: {e}"))
        };
        let load_net = |name: &str, net: &mut Mlp| -> Result<(), String> {
            net.load_vec(&need(name)?).map_err(|e| format!("`{name}`: {e}"))
        };
        match self {
            Agent::Sac(s) => {
                load_net("actor", &mut s.actor)?;
                load_net("critic", &mut s.critic)?;
                load_net("critic_target", &mut s.critic_target)?;
                let la = need("log_alpha")?;
                if la.len() != 1 {
                    return Err(format!("`log_alpha` has {} values, expected 1", la.len()));
                }
                tch::no_grad(|| {
                    s.log_alpha.copy_(&Tensor::from_slice(&la).to_device(s.log_alpha.device()))
                });
                load_opt("actor", &mut s.actor_opt)?;
                load_opt("critic", &mut s.critic_opt)?;
                load_opt("alpha", &mut s.alpha_opt)?;
            }
            Agent::Td3(d) => {
                load_net("actor", &mut d.actor)?;
                load_net("actor_target", &mut d.actor_target)?;
                load_net("critic", &mut d.critic)?;
                load_net("critic_target", &mut d.critic_target)?;
                load_opt("actor", &mut d.actor_opt)?;
                load_opt("critic", &mut d.critic_opt)?;
                d.updates = need_step("updates")?;
            }
        }
        Ok(())
    }
}

/// What a checkpoint stores of an agent.
#[derive(Debug, Clone, PartialEq)]
pub struct AgentState {
    /// Networks, target networks and optimiser moments, by name.
    pub arrays: Vec<(String, Vec<f32>)>,
    /// Optimiser step counts (and TD3's update count), by name.
    pub counters: Vec<(String, u64)>,
}

/// How an actor's raw output becomes an action.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum PolicyHead {
    /// Raw output `[mean, log_std]` (2A); action `tanh(mean + std * n)`.
    Sac,
    /// Raw output `a` (A); action `clip(tanh(a) + sigma * n, -1, 1)`.
    Td3 { exploration_noise: f32 },
}

/// Whether to act with the policy's exploration noise or deterministically.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Noise {
    /// SAC: a sample of the policy; TD3: Gaussian exploration noise (as in its replay buffer).
    Explore,
    /// The noiseless policy (`tanh(mean)` / `tanh(a)`).
    Deterministic,
}

impl PolicyHead {
    /// Raw output width for `act_dim`.
    pub fn raw_dim(self, act_dim: usize) -> usize {
        match self {
            PolicyHead::Sac => 2 * act_dim,
            PolicyHead::Td3 { .. } => act_dim,
        }
    }

    /// The action from one row of raw output; noise (when used) comes from `rng`.
    pub fn action(
        self,
        raw: &[f32],
        act_dim: usize,
        noise: Noise,
        rng: &mut ChaCha8Rng,
        out: &mut Vec<f32>,
    ) {
        let n = match noise {
            Noise::Explore => normals(rng, act_dim),
            Noise::Deterministic => vec![0.0; act_dim],
        };
        match self {
            PolicyHead::Sac => {
                for j in 0..act_dim {
                    let log_std = raw[act_dim + j].clamp(-20.0, 2.0);
                    out.push((raw[j] + log_std.exp() * n[j]).tanh());
                }
            }
            PolicyHead::Td3 { exploration_noise } => {
                for j in 0..act_dim {
                    out.push((raw[j].tanh() + exploration_noise * n[j]).clamp(-1.0, 1.0));
                }
            }
        }
    }
}

/// Raw actor outputs for a batch of agent inputs `[n, D]` (row-major), as host floats.
pub fn actor_raw(actor: &Mlp, inputs: &[f32], n: usize, device: Device) -> Vec<f32> {
    let d = inputs.len() / n.max(1);
    let x = Tensor::from_slice(inputs).view([n as i64, d as i64]).to_device(device);
    tch::no_grad(|| tensor_to_vec(&actor.forward(&x)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn a_mirrored_encoder_sees_the_mirrored_observation_and_goal_and_mirrors_actions_back() {
        use pdt_envs::ant_dir::Symmetry;
        let fam = pdt_envs::family("ant_dir").unwrap();
        let plain = TaskEncoder::for_family(fam.as_ref()).unwrap();
        let mirrors = Mirror::for_family("ant_dir");
        assert_eq!(mirrors.len(), 3);
        assert!(Mirror::for_family("cheetah_vel").is_empty());
        let obs: Vec<f32> = (0..27).map(|i| i as f32 * 0.1 - 1.0).collect();
        for (m, sym) in mirrors.iter().zip(Symmetry::ALL) {
            assert!(m.fits(27, 8, 2));
            let enc = TaskEncoder { mirror: Some(m.clone()), ..plain.clone() };
            let (mut a, mut b) = (vec![], vec![]);
            enc.encode(&obs, 3, &mut a);
            let mobs: Vec<f32> = sym.observation().apply(&obs).iter().map(|&v| v as f32).collect();
            plain.encode(&mobs, 3, &mut b);
            // The task feature: (cos, sin) of the mirrored goal.
            let g = sym.goal(pdt_envs::ant_dir::GOALS[3]);
            b.truncate(27);
            b.extend([g.cos() as f32, g.sin() as f32]);
            for (x, y) in a.iter().zip(&b) {
                assert!((x - y).abs() < 1e-6, "{}: {a:?} vs {b:?}", m.name);
            }
            let mut act: Vec<f32> = (0..8).map(|i| i as f32 * 0.2 - 0.7).collect();
            let want: Vec<f32> = sym.action().apply(&act).iter().map(|&v| v as f32).collect();
            enc.decode_action(&mut act);
            assert_eq!(act, want);
            plain.decode_action(&mut act);
            assert_eq!(act, want, "no mirror: unchanged");
        }
    }

    #[test]
    fn encoders_of_the_mujoco_families() {
        let cd =
            TaskEncoder::for_family(pdt_envs::family("cheetah_dir").unwrap().as_ref()).unwrap();
        assert_eq!(cd.input_dim(), 20);
        let obs: Vec<f32> = (0..20).map(|i| i as f32).collect();
        let mut out = vec![];
        cd.encode(&obs, 1, &mut out);
        assert_eq!(out.len(), 20);
        assert!(!out[..19].contains(&17.0), "torso x is dropped");
        assert_eq!(out[19], -1.0);
        let ant = TaskEncoder::for_family(pdt_envs::family("ant_dir").unwrap().as_ref()).unwrap();
        assert_eq!(ant.input_dim(), 29);
        let f = &ant.task_features[0];
        assert!((f[0] * f[0] + f[1] * f[1] - 1.0).abs() < 1e-6);
        let vel =
            TaskEncoder::for_family(pdt_envs::family("cheetah_vel").unwrap().as_ref()).unwrap();
        assert_eq!(vel.task_features[39], vec![3.0]);
    }

    #[test]
    fn normals_look_standard() {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let v = normals(&mut rng, 100_001);
        assert_eq!(v.len(), 100_001);
        let mean = v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
        let var = v.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / v.len() as f64;
        assert!(mean.abs() < 0.01 && (var - 1.0).abs() < 0.02, "{mean} {var}");
    }
}
