//! Meta-World reach's scripted policies (Meta-World's `SawyerReachV3Policy`, with noise).

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use pdt_data::Trajectory;

use crate::collect_scripted::{
    play_set, CollectConfig, CollectError, EpisodeLog, ScriptedPolicies,
};
use crate::metaworld_reach::{self as reach, MetaWorldReach, MetaWorldReachFamily};
use crate::mujoco_env::standard_normal;
use crate::{Env, EnvFamily};
use pdt_data::mode::{Mode, Set};

/// Meta-World reach: standard deviation of the expert's (and medium policy's) action noise on
/// every dimension, Meta-World's test-harness model `a ~ N(a, (pct * 2)^2)` at pct 0.1, under which
/// Meta-World's own tests require reach's expert to succeed (spec §3: measured 100 % ever-success).
pub const REACH_ACTION_NOISE: f64 = 0.2;
/// Meta-World reach: standard deviation (m) of the medium policy's per-coordinate goal error,
/// drawn once per episode: it settles about 0.17 m from the goal (outside the 0.05 m success
/// radius), which earns about half the expert's return (measured over the paper's 20 tasks, 200
/// episodes each: medium 2,629, expert 4,826, random 777; medium succeeds in 11 % of episodes).
pub const REACH_MEDIUM_GOAL_NOISE: f64 = 0.1;

/// One episode of `mode` on a Meta-World reach task (`env`, reset here); all randomness comes from
/// `rng`. Returns the episode and whether it ever succeeded.
///
/// The recorded observations are the ML1 ones (goal slot zeroed); the expert and medium policies
/// read the true goal from the environment, as Meta-World's scripted policies need it (spec §4.2).
pub fn run_reach_episode(
    env: &mut MetaWorldReach,
    task: usize,
    mode: Mode,
    noise: f64,
    rng: &mut ChaCha8Rng,
) -> Result<(Trajectory, bool), CollectError> {
    let goal = env.goal();
    let aim = match mode {
        Mode::Medium => goal.map(|g| g + REACH_MEDIUM_GOAL_NOISE * standard_normal(rng)),
        Mode::Expert | Mode::Random => goal,
    };
    let mut log = EpisodeLog::new(reach::OBS_DIM, reach::ACT_DIM, reach::HORIZON);
    let mut succeeded = false;
    let mut obs = Env::reset(env, 0);
    loop {
        let action: [f32; 4] = match mode {
            Mode::Expert | Mode::Medium => {
                let full = env.obs_f64();
                let a = reach::expert_action([full[0], full[1], full[2]], aim);
                // The noise is added to the f32 action in f64 and rounded back, as numpy's
                // `normal(a_f32, std)` returns f64 that the f32 dataset then stores.
                // With no noise the expert's action is kept as it is (no draw, no rounding).
                if noise > 0.0 {
                    a.map(|v| (f64::from(v) + noise * standard_normal(rng)) as f32)
                } else {
                    a
                }
            }
            Mode::Random => std::array::from_fn(|_| rng.random_range(-1.0f32..=1.0)),
        };
        let step = Env::step(env, &action)?;
        succeeded |= step.success == Some(true);
        let ended = log.record(&obs, &action, &step);
        obs = step.obs;
        if ended {
            break;
        }
    }
    Ok((log.finish(reach::ENV_NAME, task, mode)?, succeeded))
}

/// Meta-World reach's [`ScriptedPolicies`].
pub struct ReachPolicies;

impl ScriptedPolicies for ReachPolicies {
    fn name(&self) -> &'static str {
        reach::ENV_NAME
    }

    fn family(&self) -> Box<dyn EnvFamily> {
        Box::new(MetaWorldReachFamily::default())
    }

    /// The 20 tasks of the paper's split (1..=20; the family's other 30 tasks are in no split).
    fn default_tasks(&self) -> Vec<usize> {
        let mut t: Vec<usize> =
            reach::TRAIN_TASKS.iter().chain(&reach::TEST_TASKS).copied().collect();
        t.sort_unstable();
        t
    }

    /// The paper's "200 episodes for each task".
    fn default_episodes(&self) -> usize {
        200
    }

    fn policy_description(&self, mode: Mode) -> &'static str {
        match mode {
            Mode::Expert => {
                "a = f32(5 (goal - hand), 0) + N(0, s^2) per dimension, s = action_noise_std \
                 (Meta-World's SawyerReachV3Policy; s = 0.2 is its test harness's noise at \
                 pct 0.1; the true goal is read from the env, the recorded observation hides \
                 it)"
            }
            Mode::Medium => {
                "g' = goal + N(0, 0.1^2) per coordinate, drawn once per episode; a = \
                 f32(5 (g' - hand), 0) + N(0, s^2) per dimension, s = action_noise_std"
            }
            Mode::Random => "a ~ Uniform[-1, 1] per dimension (the action space)",
        }
    }

    fn takes_action_noise(&self) -> bool {
        true
    }

    /// [`REACH_ACTION_NOISE`].
    fn default_action_noise(&self) -> f64 {
        REACH_ACTION_NOISE
    }

    fn episodes(
        &self,
        cfg: &CollectConfig,
        task: usize,
        mode: Mode,
        set: Set,
        episodes: usize,
    ) -> Result<(Vec<Trajectory>, Option<f64>), CollectError> {
        // One simulator for the whole set: every reset restores the same start state, so the
        // episodes do not depend on what ran before them (tests/it/metaworld_parity.rs).
        let mut sim = MetaWorldReachFamily::default().make_env(task)?;
        let noise = cfg.reach_action_noise;
        play_set(cfg, task, mode, set, episodes, true, |rng| {
            run_reach_episode(&mut sim, task, mode, noise, rng)
        })
    }
}
