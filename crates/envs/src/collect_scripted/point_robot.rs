//! The point robot's scripted policies (their formulas: `policy_description`, in the card).

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use pdt_data::Trajectory;

use super::{
    episode_rng, normal, CollectConfig, CollectError, EpisodeLog, Mode, ScriptedPolicies, Set,
};
use crate::point_robot::{self, PointRobot, ACT_DIM, ENV_NAME, MAX_SPEED, NUM_TASKS, OBS_DIM};
use crate::{Env, EnvFamily};

/// Standard deviation of the expert's per-coordinate action noise.
pub const EXPERT_ACTION_NOISE: f64 = 0.01;
/// Standard deviation of the medium policy's per-episode, per-coordinate goal error.
pub const MEDIUM_GOAL_NOISE: f64 = 0.5;
/// Standard deviation of the medium policy's per-coordinate action noise.
pub const MEDIUM_ACTION_NOISE: f64 = 0.05;

/// Runs one episode of `mode` on `task`; all randomness comes from `rng`.
pub fn run_episode(
    task: usize,
    mode: Mode,
    rng: &mut ChaCha8Rng,
) -> Result<Trajectory, CollectError> {
    let goal = point_robot::goal(task)?;
    let mut env = PointRobot::new(goal);
    // The medium policy's misremembered goal is fixed for the whole episode, so it goes
    // consistently to the wrong place instead of jittering around the right one.
    let aim = match mode {
        Mode::Medium => {
            [goal[0] + normal(rng, MEDIUM_GOAL_NOISE), goal[1] + normal(rng, MEDIUM_GOAL_NOISE)]
        }
        Mode::Expert | Mode::Random => goal,
    };
    let mut log = EpisodeLog::new(OBS_DIM, ACT_DIM, env.horizon());
    let mut obs = env.reset(0);
    loop {
        let pos = env.position();
        let action: [f32; 2] = match mode {
            Mode::Expert | Mode::Medium => {
                let noise =
                    if mode == Mode::Expert { EXPERT_ACTION_NOISE } else { MEDIUM_ACTION_NOISE };
                let mut a = [0.0f32; 2];
                for (j, v) in a.iter_mut().enumerate() {
                    *v = point_robot::clip_speed(aim[j] - pos[j] + normal(rng, noise));
                }
                a
            }
            Mode::Random => {
                [rng.random_range(-MAX_SPEED..=MAX_SPEED), rng.random_range(-MAX_SPEED..=MAX_SPEED)]
            }
        };
        let step = env.step(&action)?;
        let ended = log.record(&obs, &action, &step);
        obs = step.obs;
        if ended {
            break;
        }
    }
    log.finish().map_err(|source| CollectError::Data { env: ENV_NAME, task, mode, source })
}

/// The point robot's [`ScriptedPolicies`].
pub(super) struct PointRobotPolicies;

impl ScriptedPolicies for PointRobotPolicies {
    fn name(&self) -> &'static str {
        ENV_NAME
    }

    fn family(&self) -> Box<dyn EnvFamily> {
        Box::new(point_robot::PointRobotFamily::default())
    }

    /// Every goal.
    fn default_tasks(&self) -> Vec<usize> {
        (0..NUM_TASKS).collect()
    }

    fn default_episodes(&self) -> usize {
        100
    }

    fn policy_description(&self, mode: Mode) -> &'static str {
        match mode {
            Mode::Expert => {
                "a = clip(goal - pos + N(0, 0.01^2) per coordinate, -0.1, 0.1): straight to the \
                 goal at full speed"
            }
            Mode::Medium => {
                "g' = goal + N(0, 0.5^2) per coordinate, drawn once per episode; a = clip(g' - pos \
                 + N(0, 0.05^2) per coordinate, -0.1, 0.1)"
            }
            Mode::Random => "a ~ Uniform[-0.1, 0.1] per coordinate",
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
        let t = (0..episodes)
            .map(|e| {
                if cfg.interrupt.is_set() {
                    return Err(CollectError::Interrupted);
                }
                run_episode(task, mode, &mut episode_rng(cfg.seed, task, mode, set, e))
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok((t, None))
    }
}
