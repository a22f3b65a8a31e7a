//! Dial's scripted policies: the original collector's PI controller with DART noise.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use pdt_data::Trajectory;

use crate::collect_scripted::{
    play_set, CollectConfig, CollectError, EpisodeLog, ScriptedPolicies,
};
use crate::dial::{self, Dial, DialExpert, DialFamily};
use crate::mujoco_env::standard_normal;
use crate::{Env, EnvFamily};
use pdt_data::mode::{Mode, Set};

/// Dial: the expert's per-episode DART noise amounts (the original collector's, spec §3.2), drawn
/// uniformly; the noise on joint j is N(0, (|c_low[j]| amount)^2), plus U(0, 0.1) on joint 1's
/// standard deviation, redrawn every 1 or 2 steps (drawn per episode).
pub const DIAL_DART_AMOUNTS: [f64; 3] = [0.0, 0.2, 0.3];
/// Dial: standard deviation (rad) of the medium policy's per-episode error on each arm joint of
/// its target pose (it then settles near, not at, the key: see `docs/dial.md` for its measured
/// success rate).
pub const DIAL_MEDIUM_TARGET_NOISE: f64 = 0.15;

/// One Dial episode of `mode` on `env` (reset here from a perturbed start); all randomness comes
/// from `rng`. Returns the episode and whether it reached the digit.
///
/// As in the original collector (DART), the expert's and medium policy's recorded action is the
/// controller's clean action and the executed one carries the noise, so the data teaches recovery
/// from the states the noise leads to; replaying a noisy episode's recorded actions does not
/// reproduce it.
pub fn run_dial_episode(
    env: &mut Dial,
    mode: Mode,
    rng: &mut ChaCha8Rng,
) -> Result<(Trajectory, bool), CollectError> {
    let task = env.digit();
    let start = dial::noisy_start(rng)?;
    let mut obs: Vec<f32> = env.reset_from(&start)?.iter().map(|&v| v as f32).collect();
    // The medium policy aims at the hover pose misremembered once per episode (arm joints only).
    let mut aim = dial::targets()?.hover[task];
    if mode == Mode::Medium {
        for v in aim.iter_mut().take(6) {
            *v += DIAL_MEDIUM_TARGET_NOISE * standard_normal(rng);
        }
    }
    let mut expert = DialExpert::with_target(aim);
    let amount = DIAL_DART_AMOUNTS[rng.random_range(0..DIAL_DART_AMOUNTS.len())];
    let hold = rng.random_range(1..=2usize);
    let mut noise = [0.0f64; dial::ACT_DIM];
    let mut log = EpisodeLog::new(dial::OBS_DIM, dial::ACT_DIM, dial::HORIZON);
    let mut succeeded = false;
    for t in 0.. {
        let (recorded, executed): ([f32; dial::ACT_DIM], [f32; dial::ACT_DIM]) = match mode {
            Mode::Expert | Mode::Medium => {
                let a = expert.act(&obs);
                if amount > 0.0 && t % hold == 0 {
                    let extra = rng.random_range(0.0..0.1);
                    for (j, n) in noise.iter_mut().enumerate() {
                        let std = dial::C_LOW[j].abs() * amount + if j == 0 { extra } else { 0.0 };
                        *n = std * standard_normal(rng);
                    }
                }
                let executed = std::array::from_fn(|j| (f64::from(a[j]) + noise[j]) as f32);
                (a, executed)
            }
            Mode::Random => {
                let a = std::array::from_fn(|j| {
                    rng.random_range(dial::C_LOW[j] as f32..=dial::C_HIGH[j] as f32)
                });
                (a, a)
            }
        };
        let step = Env::step(env, &executed)?;
        succeeded |= step.success == Some(true);
        let ended = log.record(&obs, &recorded, &step);
        obs = step.obs;
        if ended {
            break;
        }
    }
    Ok((log.finish(dial::ENV_NAME, task, mode)?, succeeded))
}

/// Dial's [`ScriptedPolicies`].
pub struct DialPolicies;

impl ScriptedPolicies for DialPolicies {
    fn name(&self) -> &'static str {
        dial::ENV_NAME
    }

    fn family(&self) -> Box<dyn EnvFamily> {
        Box::new(DialFamily)
    }

    /// The 10 digits.
    fn default_tasks(&self) -> Vec<usize> {
        (0..dial::NUM_TASKS).collect()
    }

    /// The paper's "200 episodes for each task".
    fn default_episodes(&self) -> usize {
        200
    }

    fn policy_description(&self, mode: Mode) -> &'static str {
        match mode {
            Mode::Expert => {
                "start: init pose + U(-0.1, 0.1) per joint, joint 1 + U(0, 0.2), joint 2 + \
                 U(-0.2, 0), settled back by the PI controller; a = the original's PI \
                 controller toward the digit's hover pose (recorded); executed: a + DART noise \
                 N(0, (|c_low| m)^2), m drawn per episode from {0, 0.2, 0.3} (joint 1's std + \
                 U(0, 0.1)), redrawn every 1 or 2 steps (drawn per episode)"
            }
            Mode::Medium => {
                "as the expert, toward the hover pose with N(0, 0.15^2) rad added to each arm \
                 joint once per episode (it settles near, not always within reach of, the key)"
            }
            Mode::Random => "a ~ Uniform[c_low, c_high] per dimension (the action box)",
        }
    }

    fn episodes(
        &self,
        cfg: &CollectConfig,
        task: usize,
        mode: Mode,
        set: Set,
        episodes: usize,
    ) -> Result<(Vec<Trajectory>, Option<f64>), CollectError> {
        // One simulator for the whole set: every episode starts with a full reset.
        let mut sim = DialFamily.make_env(task)?;
        play_set(cfg, task, mode, set, episodes, true, |rng| run_dial_episode(&mut sim, mode, rng))
    }
}
