//! 2-D point-robot navigation, following PEARL's `point-robot` / `sparse-point-robot`
//! environments (Rakelly et al. 2019, `rlkit/envs/point_robot.py`), with the dense reward.
//!
//! - State: the position `(x, y)`; the observation is the state (`obs_dim = 2`).
//! - Action: a velocity `(vx, vy)` (`act_dim = 2`), clipped to `[-0.1, 0.1]` per coordinate.
//! - Dynamics: `pos <- pos + clip(action)`; every episode starts at the origin.
//! - Reward: `-|pos - goal|` (Euclidean) measured *after* the step.
//! - Episodes last [`HORIZON`] = 20 steps and are then truncated; the MDP never terminates.
//! - Tasks: [`NUM_TASKS`] = 40 goals on the upper half of the unit circle at angles
//!   `linspace(0, pi, 40)`.
//!
//! The start is deterministic (PEARL's `reset` also puts the robot at 0), so `reset(seed)` ignores
//! its seed and an episode is a pure function of the task and the actions. `docs/point-robot.md`
//! describes the family, its splits, and how it differs from PEARL's.
//!
//! Its datasets are collected by scripted policies ([`PointRobotPolicies`], below: expert, medium,
//! random), on the machinery every scripted family shares (`collect_scripted`).

use pdt_data::Trajectory;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::collect_scripted::{
    play_set, CollectConfig, CollectError, EpisodeLog, ScriptedFamily, ScriptedPolicies,
};
use crate::mujoco_env::standard_normal;
use crate::replay::{replay_from_reset, ReplayResult};
use crate::{ActionBounds, Env, EnvError, EnvFamily, EnvPreset, StepResult};
use pdt_data::mode::{Mode, Set};

/// Family name, as used in file names (`point_robot-3-expert.safetensors`).
pub const ENV_NAME: &str = "point_robot";
/// Number of tasks (goals) in the family.
pub const NUM_TASKS: usize = 40;
/// Episode length: `step` reports `truncated` at this step.
pub const HORIZON: usize = 20;
/// Largest speed per coordinate and step; actions are clipped to `[-MAX_SPEED, MAX_SPEED]`.
pub const MAX_SPEED: f32 = 0.1;
/// Observation size: the position `(x, y)`.
pub const OBS_DIM: usize = 2;
/// Action size: the velocity `(vx, vy)`.
pub const ACT_DIM: usize = 2;
/// Test tasks of the `default` split: spread evenly over the arc, so every test goal lies between
/// two training goals (interpolation).
pub const DEFAULT_TEST_TASKS: [usize; 5] = [2, 10, 18, 26, 34];
/// Test tasks of the `ood` split: the five largest angles, so no training goal lies beyond them
/// (extrapolation, like the paper's Ant-Dir out-of-distribution split).
pub const OOD_TEST_TASKS: [usize; 5] = [35, 36, 37, 38, 39];
/// Split names, the default first.
pub const SPLIT_NAMES: [&str; 2] = ["default", "ood"];

/// Angle of task `task`'s goal, in radians: `linspace(0, pi, 40)[task]`.
///
/// Computed like numpy's `linspace` (`start + i * step`, last point exactly `stop`) so the goals
/// match a Python re-implementation bit for bit in f64.
pub fn goal_angle(task: usize) -> Result<f64, EnvError> {
    EnvError::check_task(ENV_NAME, task, NUM_TASKS)?;
    if task == NUM_TASKS - 1 {
        return Ok(std::f64::consts::PI);
    }
    let step = std::f64::consts::PI / (NUM_TASKS - 1) as f64;
    Ok(task as f64 * step)
}

/// Goal of task `task` in f64: `(cos a, sin a)` with `a = goal_angle(task)`. The environment uses
/// these values rounded to f32 (see [`goal`]).
pub fn goal_f64(task: usize) -> Result<[f64; 2], EnvError> {
    let a = goal_angle(task)?;
    Ok([a.cos(), a.sin()])
}

/// Goal of task `task`, as the environment uses it (f32, like the observations).
pub fn goal(task: usize) -> Result<[f32; 2], EnvError> {
    let [x, y] = goal_f64(task)?;
    Ok([x as f32, y as f32])
}

/// Reward at position `pos` for goal `goal`: minus the Euclidean distance.
pub fn reward(pos: [f32; 2], goal: [f32; 2]) -> f32 {
    let dx = pos[0] - goal[0];
    let dy = pos[1] - goal[1];
    -(dx * dx + dy * dy).sqrt()
}

/// Clips one action coordinate to `[-MAX_SPEED, MAX_SPEED]`.
pub fn clip_speed(v: f32) -> f32 {
    v.clamp(-MAX_SPEED, MAX_SPEED)
}

/// One point-robot task: a fixed goal, the robot's position and the step count.
#[derive(Debug, Clone, PartialEq)]
pub struct PointRobot {
    goal: [f32; 2],
    pos: [f32; 2],
    /// Steps taken in the current episode.
    t: usize,
}

impl PointRobot {
    /// An environment with an arbitrary goal, ready at the origin (no `reset` needed first, as in
    /// PEARL, whose constructor also starts at the origin).
    pub fn new(goal: [f32; 2]) -> Self {
        Self { goal, pos: [0.0, 0.0], t: 0 }
    }

    /// The environment of task `task` of the family.
    pub fn for_task(task: usize) -> Result<Self, EnvError> {
        Ok(Self::new(goal(task)?))
    }

    pub fn goal(&self) -> [f32; 2] {
        self.goal
    }

    /// Current position (the current observation).
    pub fn position(&self) -> [f32; 2] {
        self.pos
    }

    /// Steps taken in the current episode.
    pub fn steps(&self) -> usize {
        self.t
    }

    /// Whether the episode has reached its time limit (further steps are refused until `reset`).
    pub fn is_finished(&self) -> bool {
        self.t >= HORIZON
    }
}

impl Env for PointRobot {
    fn obs_dim(&self) -> usize {
        OBS_DIM
    }

    fn act_dim(&self) -> usize {
        ACT_DIM
    }

    fn horizon(&self) -> usize {
        HORIZON
    }

    /// Puts the robot at the origin. The start is deterministic, so `seed` is unused: the trait
    /// takes it for families with start-state noise.
    fn reset(&mut self, _seed: u64) -> Vec<f32> {
        self.pos = [0.0, 0.0];
        self.t = 0;
        self.pos.to_vec()
    }

    fn step(&mut self, action: &[f32]) -> Result<StepResult, EnvError> {
        // Check everything before changing any state, so a refused step leaves the episode as it
        // was and the caller may retry with a corrected action.
        if self.is_finished() {
            return Err(EnvError::Finished { env: ENV_NAME.into() });
        }
        if action.len() != ACT_DIM {
            return Err(EnvError::ActionDim {
                env: ENV_NAME.into(),
                got: action.len(),
                expected: ACT_DIM,
            });
        }
        if let Some((index, &value)) = action.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            // Clipping would turn +-inf into +-0.1 and NaN is unordered; a non-finite action is a
            // bug in the policy, so refuse it rather than silently repair it.
            return Err(EnvError::NonFiniteAction { env: ENV_NAME.into(), index, value });
        }
        self.pos[0] += clip_speed(action[0]);
        self.pos[1] += clip_speed(action[1]);
        self.t += 1;
        Ok(StepResult {
            obs: self.pos.to_vec(),
            reward: reward(self.pos, self.goal),
            // Navigation has no failure state: the episode only ends by the time limit.
            terminated: false,
            truncated: self.t >= HORIZON,
            success: None,
        })
    }
    /// A top view of the arena (the goals lie on the unit half circle; 20 steps of at most 0.1
    /// reach 2 from the origin, mostly inside 1.5).
    fn view(&mut self) -> Result<crate::render::View<'_>, EnvError> {
        let plane = crate::render::Plane { position: self.pos, goal: Some(self.goal), extent: 1.5 };
        Ok(crate::render::View::Plane(plane))
    }
}

/// The 40-task point-robot family (see the module docs). Build it with `default()`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PointRobotFamily {
    /// Not a unit struct, so that options (e.g. more tasks) can be added later without breaking
    /// callers, who all construct it with `default()`.
    _private: (),
}

impl PointRobotFamily {
    /// The `(train, test)` tasks of a split, or `None` for an unknown name.
    fn split_tasks(name: &str) -> Option<(Vec<usize>, Vec<usize>)> {
        let test: &[usize] = match name {
            "default" => &DEFAULT_TEST_TASKS,
            "ood" => &OOD_TEST_TASKS,
            _ => return None,
        };
        let train = (0..NUM_TASKS).filter(|t| !test.contains(t)).collect();
        Some((train, test.to_vec()))
    }
}

impl EnvFamily for PointRobotFamily {
    fn name(&self) -> &str {
        ENV_NAME
    }

    fn num_tasks(&self) -> usize {
        NUM_TASKS
    }

    fn preset(&self) -> EnvPreset {
        EnvPreset {
            obs_dim: OBS_DIM,
            act_dim: ACT_DIM,
            horizon: HORIZON,
            // Returns of sensible behaviour lie between about -21 (random actions; standing still
            // gives -20) and -3 (optimal, for a diagonal goal), so return-to-go / 10 is O(1).
            rtg_scale: 10.0,
            // Like cheetah_vel's G* = 0: 0 is an upper bound on the return that good episodes
            // approach, so conditioning on it asks for the best behaviour.
            target_return: 0.0,
            prompt_length: 5,
        }
    }

    fn split_names(&self) -> Vec<String> {
        SPLIT_NAMES.iter().map(|s| (*s).to_owned()).collect()
    }

    fn split(&self, name: &str) -> Result<(Vec<usize>, Vec<usize>), EnvError> {
        Self::split_tasks(name).ok_or_else(|| EnvError::unknown_split(ENV_NAME, name, &SPLIT_NAMES))
    }

    /// `{"goal": [x, y], "angle": a}` in f64 (the environment rounds the goal to f32).
    fn task_params(&self, task: usize) -> Result<serde_json::Value, EnvError> {
        let angle = goal_angle(task)?;
        let [x, y] = goal_f64(task)?;
        Ok(serde_json::json!({ "goal": [x, y], "angle": angle }))
    }

    fn make(&self, task: usize) -> Result<Box<dyn Env>, EnvError> {
        Ok(Box::new(PointRobot::for_task(task)?))
    }

    /// The speed is clipped to [-MAX_SPEED, MAX_SPEED] per coordinate.
    /// No simulated time: `promptdt render`'s default rate.
    fn render_fps(&self) -> u32 {
        20
    }

    fn action_bounds(&self) -> ActionBounds {
        ActionBounds::symmetric(MAX_SPEED, ACT_DIM)
    }

    /// [`PointRobotPolicies`].
    fn scripted(&self) -> Option<ScriptedFamily> {
        Some(ScriptedFamily::new(&PointRobotPolicies))
    }

    fn rl_preset(&self) -> Option<&'static str> {
        Some(include_str!("../../../configs/collect/point_robot.toml"))
    }

    /// The goal `[x, y]` (f64 rounded to f32).
    fn task_features(&self, task: usize) -> Result<Vec<f32>, EnvError> {
        Ok(goal_f64(task)?.iter().map(|&v| v as f32).collect())
    }

    /// From the reset state at the origin (no `init`).
    fn replay(
        &self,
        task: usize,
        init: Option<&str>,
        actions: &[Vec<f32>],
    ) -> Result<ReplayResult, EnvError> {
        replay_from_reset(&mut PointRobot::for_task(task)?, ENV_NAME, task, init, actions)
    }
}

// The scripted policies that collect the datasets (the machinery: `collect_scripted`; their
// formulas: `policy_description`, in the card).

fn normal(rng: &mut ChaCha8Rng, std: f64) -> f32 {
    (std * standard_normal(rng)) as f32
}

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
    let goal = goal(task)?;
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
                    *v = clip_speed(aim[j] - pos[j] + normal(rng, noise));
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
    log.finish(ENV_NAME, task, mode)
}

/// The point robot's [`ScriptedPolicies`].
pub struct PointRobotPolicies;

impl ScriptedPolicies for PointRobotPolicies {
    fn name(&self) -> &'static str {
        ENV_NAME
    }

    fn family(&self) -> Box<dyn EnvFamily> {
        Box::new(PointRobotFamily::default())
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
        play_set(cfg, task, mode, set, episodes, false, |rng| {
            Ok((run_episode(task, mode, rng)?, false))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(env: &mut PointRobot, actions: &[[f32; 2]]) -> Vec<StepResult> {
        env.reset(0);
        actions.iter().map(|a| env.step(a).expect("valid step")).collect()
    }

    #[test]
    fn reward_is_minus_distance_after_the_step() {
        let mut env = PointRobot::new([0.3, 0.4]);
        assert_eq!(env.reset(0), vec![0.0, 0.0]);
        let r = env.step(&[0.1, 0.0]).expect("step");
        assert_eq!(r.obs, vec![0.1, 0.0]);
        // Distance from (0.1, 0) to (0.3, 0.4) is sqrt(0.04 + 0.16).
        let want = -((0.2f32 * 0.2) + 0.4 * 0.4).sqrt();
        assert!((r.reward - want).abs() < 1e-6, "{} vs {want}", r.reward);
        assert_eq!(r.reward, reward([0.1, 0.0], [0.3, 0.4]));
        // At the goal the reward is exactly zero.
        assert_eq!(reward([0.3, 0.4], [0.3, 0.4]), 0.0);
    }

    #[test]
    fn actions_are_clipped_per_coordinate() {
        let mut env = PointRobot::new([1.0, 0.0]);
        env.reset(0);
        let r = env.step(&[5.0, -0.05]).expect("step");
        assert_eq!(r.obs, vec![0.1, -0.05]);
        let r = env.step(&[-0.5, -3.0]).expect("step");
        assert!((r.obs[0] - 0.0).abs() < 1e-7 && (r.obs[1] - -0.15).abs() < 1e-7, "{:?}", r.obs);
        assert_eq!(clip_speed(0.1), 0.1);
        assert_eq!(clip_speed(-0.2), -0.1);
        assert_eq!(clip_speed(0.03), 0.03);
    }

    #[test]
    fn truncated_at_step_20_never_terminated() {
        let mut env = PointRobot::for_task(0).expect("task 0");
        let results = run(&mut env, &[[0.1, 0.1]; HORIZON]);
        for (t, r) in results.iter().enumerate() {
            assert!(!r.terminated, "terminated at step {t}");
            assert_eq!(r.truncated, t == HORIZON - 1, "truncated flag at step {t}");
        }
        assert!(env.is_finished());
        assert_eq!(env.step(&[0.0, 0.0]), Err(EnvError::Finished { env: ENV_NAME.into() }));
        // Reset starts a fresh episode at the origin.
        assert_eq!(env.reset(7), vec![0.0, 0.0]);
        assert_eq!(env.steps(), 0);
        assert!(env.step(&[0.0, 0.0]).is_ok());
    }

    #[test]
    fn episodes_are_deterministic_and_ignore_the_seed() {
        let actions: Vec<[f32; 2]> =
            (0..HORIZON).map(|t| [0.01 * t as f32 - 0.07, 0.3 - 0.02 * t as f32]).collect();
        let mut a = PointRobot::for_task(13).expect("task");
        let mut b = PointRobot::for_task(13).expect("task");
        let first = run(&mut a, &actions);
        assert_eq!(b.reset(12345), vec![0.0, 0.0]);
        let second: Vec<StepResult> = actions.iter().map(|x| b.step(x).expect("step")).collect();
        assert_eq!(first, second);
        // Running again on the same env after reset gives the same episode.
        assert_eq!(run(&mut a, &actions), first);
    }

    #[test]
    fn wrong_action_length_is_an_error() {
        let mut env = PointRobot::for_task(0).expect("task");
        for bad in [&[][..], &[0.1][..], &[0.1, 0.1, 0.1][..]] {
            assert_eq!(
                env.step(bad),
                Err(EnvError::ActionDim { env: ENV_NAME.into(), got: bad.len(), expected: 2 })
            );
        }
        // Refused steps do not advance the episode.
        assert_eq!(env.steps(), 0);
        assert_eq!(env.position(), [0.0, 0.0]);
    }

    #[test]
    fn non_finite_actions_are_errors() {
        let mut env = PointRobot::for_task(0).expect("task");
        for (action, index) in
            [([f32::NAN, 0.0], 0), ([0.0, f32::INFINITY], 1), ([f32::NEG_INFINITY, 0.0], 0)]
        {
            match env.step(&action) {
                Err(EnvError::NonFiniteAction { index: i, value, .. }) => {
                    assert_eq!(i, index);
                    assert!(!value.is_finite());
                }
                other => panic!("expected NonFiniteAction for {action:?}, got {other:?}"),
            }
        }
        assert_eq!(env.steps(), 0);
        assert_eq!(env.position(), [0.0, 0.0]);
    }

    #[test]
    fn greedy_returns_match_the_docs() {
        // docs/point-robot.md: -4.5 on the axes, about -3.0 on the diagonal.
        let greedy_return = |goal: [f32; 2]| {
            let mut env = PointRobot::new(goal);
            env.reset(0);
            let mut total = 0.0f64;
            for _ in 0..HORIZON {
                let p = env.position();
                let a = [goal[0] - p[0], goal[1] - p[1]];
                total += f64::from(env.step(&a).expect("step").reward);
            }
            total
        };
        assert!((greedy_return(goal(0).expect("goal")) + 4.5).abs() < 1e-4);
        let d = std::f32::consts::FRAC_1_SQRT_2;
        let diag = greedy_return([d, d]);
        assert!((diag + 3.04).abs() < 0.01, "{diag}");
    }

    #[test]
    fn goals_lie_on_the_upper_unit_half_circle() {
        assert_eq!(goal(0).expect("goal"), [1.0, 0.0]);
        let last = goal(NUM_TASKS - 1).expect("goal");
        assert_eq!(last[0], -1.0);
        assert!(last[1].abs() < 1e-7);
        for task in 0..NUM_TASKS {
            let [x, y] = goal_f64(task).expect("goal");
            assert!(((x * x + y * y).sqrt() - 1.0).abs() < 1e-12);
            assert!(y >= 0.0);
            let a = goal_angle(task).expect("angle");
            assert!((a - std::f64::consts::PI * task as f64 / 39.0).abs() < 1e-12);
        }
        assert_eq!(
            goal(NUM_TASKS),
            Err(EnvError::UnknownTask { env: ENV_NAME.into(), task: NUM_TASKS, n: NUM_TASKS })
        );
    }

    #[test]
    fn splits_partition_the_tasks() {
        let fam = PointRobotFamily::default();
        assert_eq!(fam.split_names(), vec!["default".to_owned(), "ood".to_owned()]);
        for name in SPLIT_NAMES {
            let (train, test) = fam.split(name).expect("split");
            assert_eq!(train.len(), 35);
            assert_eq!(test.len(), 5);
            let mut all: Vec<usize> = train.iter().chain(&test).copied().collect();
            all.sort_unstable();
            assert_eq!(all, (0..NUM_TASKS).collect::<Vec<_>>());
        }
        assert_eq!(fam.split("default").expect("split").1, DEFAULT_TEST_TASKS.to_vec());
        let (train, test) = fam.split("ood").expect("split");
        assert_eq!(train, (0..35).collect::<Vec<_>>());
        assert_eq!(test, (35..40).collect::<Vec<_>>());
        assert!(matches!(fam.split("nope"), Err(EnvError::UnknownSplit { .. })));
    }

    #[test]
    fn family_preset_params_and_factory() {
        let fam = PointRobotFamily::default();
        assert_eq!(fam.name(), "point_robot");
        assert_eq!(fam.num_tasks(), 40);
        let p = fam.preset();
        assert_eq!((p.obs_dim, p.act_dim, p.horizon, p.prompt_length), (2, 2, 20, 5));
        assert_eq!((p.rtg_scale, p.target_return), (10.0, 0.0));
        let params = fam.task_params(0).expect("params");
        assert_eq!(params, serde_json::json!({ "goal": [1.0, 0.0], "angle": 0.0 }));
        assert!(matches!(fam.task_params(40), Err(EnvError::UnknownTask { .. })));
        let mut env = fam.make(5).expect("make");
        assert_eq!((env.obs_dim(), env.act_dim(), env.horizon()), (2, 2, 20));
        assert_eq!(env.reset(0), vec![0.0, 0.0]);
        assert!(matches!(fam.make(40), Err(EnvError::UnknownTask { .. })));
    }
}
