//! Replaying an action sequence from a given simulator state: the Rust side of the Python parity
//! check (`scripts/mujoco/replay.py`) and of `promptdt env replay`. The JSON file format is
//! [`ReplayInput`] in and [`ReplayResult`] out; `docs/mujoco-envs.md` documents both.

use serde::{Deserialize, Serialize};

// The machinery only: a family's own replay (`EnvFamily::replay`) lives with the family and calls
// these, and the family registry (`crate::make_mujoco_env`) is the crate root's, so no family
// module and this one import each other.
use crate::mujoco_env::MujocoEnv;
use crate::{make_mujoco_env, Env, EnvError, StepResult};

/// Families that [`replay`] accepts (the MuJoCo ones).
pub const REPLAY_FAMILIES: [&str; 3] = ["cheetah_dir", "cheetah_vel", "ant_dir"];

/// A replay request (the input file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReplayInput {
    pub family: String,
    pub task: usize,
    /// Initial generalised positions (cheetah 9, ant 15).
    pub init_qpos: Vec<f64>,
    /// Initial generalised velocities (cheetah 9, ant 14).
    pub init_qvel: Vec<f64>,
    /// One action per step (cheetah 6 values, ant 8).
    pub actions: Vec<Vec<f32>>,
}

/// What a replay produced (the output file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReplayResult {
    pub family: String,
    pub task: usize,
    /// `steps + 1` observations: the one after setting the initial state, then one per step.
    pub observations: Vec<Vec<f32>>,
    /// One per step taken.
    pub rewards: Vec<f32>,
    pub terminated: Vec<bool>,
    pub truncated: Vec<bool>,
    /// Actions not applied because the episode had ended (terminated, or truncated at the
    /// horizon: 200 steps for the MuJoCo families, 500 for Meta-World reach) before them.
    pub unused_actions: usize,
    /// One per step for families with a success criterion (Meta-World reach: the hand within
    /// 0.05 m of the goal); absent for the others.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub success: Vec<bool>,
}

impl ReplayResult {
    /// A replay of `family`'s task `task` that starts at the observation `first`.
    pub(crate) fn start(family: &str, task: usize, first: Vec<f32>, steps: usize) -> Self {
        Self {
            family: family.to_string(),
            task,
            observations: vec![first],
            rewards: Vec::with_capacity(steps),
            terminated: Vec::with_capacity(steps),
            truncated: Vec::with_capacity(steps),
            unused_actions: 0,
            success: Vec::new(),
        }
    }

    /// Records the step of action `t` of `n` (its success flag where the family has one); returns
    /// whether the episode ended there, counting the actions left unused.
    fn record(&mut self, step: StepResult, t: usize, n: usize) -> bool {
        self.observations.push(step.obs);
        self.rewards.push(step.reward);
        self.terminated.push(step.terminated);
        self.truncated.push(step.truncated);
        if let Some(ok) = step.success {
            self.success.push(ok);
        }
        let ended = step.terminated || step.truncated;
        if ended {
            self.unused_actions = n - t - 1;
        }
        ended
    }
}

/// One line: the task, the steps taken, the return and whether the episode terminated.
impl std::fmt::Display for ReplayResult {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let ret: f64 = self.rewards.iter().map(|&x| x as f64).sum();
        let terminated = self.terminated.iter().any(|&t| t);
        let (family, task, steps) = (&self.family, self.task, self.rewards.len());
        write!(f, "{family} task {task}: {steps} steps, return {ret:.3}, terminated {terminated}")
    }
}

/// Sets task `task` of `family` to `(init_qpos, init_qvel)` and applies `actions` until they run
/// out or the episode ends. Errors on an unknown family or task, a state of the wrong size or with
/// non-finite values, and an action of the wrong size or with non-finite values (naming the step).
pub fn replay(
    family: &str,
    task: usize,
    init_qpos: &[f64],
    init_qvel: &[f64],
    actions: &[Vec<f32>],
) -> Result<ReplayResult, EnvError> {
    let mut env = make_mujoco_env(family, task)?;
    replay_env(&mut env, family, task, init_qpos, init_qvel, actions)
}

/// [`replay`] for a request read from a file.
pub fn replay_input(input: &ReplayInput) -> Result<ReplayResult, EnvError> {
    replay(&input.family, input.task, &input.init_qpos, &input.init_qvel, &input.actions)
}

/// [`replay`] on an environment built by the caller (e.g. Ant-Dir with the computed contact cost).
/// `family` and `task` are only recorded in the result.
pub fn replay_env(
    env: &mut MujocoEnv,
    family: &str,
    task: usize,
    init_qpos: &[f64],
    init_qvel: &[f64],
    actions: &[Vec<f32>],
) -> Result<ReplayResult, EnvError> {
    let first = env.reset_to(init_qpos, init_qvel)?;
    let mut result = ReplayResult::start(family, task, first, actions.len());
    for (t, action) in actions.iter().enumerate() {
        let resets = env.instability_resets();
        let step = env.step(action).map_err(|e| at_step(e, t))?;
        if env.instability_resets() > resets {
            // MuJoCo reset the state mid-replay: what follows is not a continuation of the input.
            return Err(EnvError::BadState {
                env: format!("{family} task {task}"),
                message: format!(
                    "the simulation diverged at step {t} (MuJoCo found a bad position, velocity \
                     or acceleration and reset it); the replay stops rather than continue from \
                     the reset state"
                ),
            });
        }
        if result.record(step, t, actions.len()) {
            break;
        }
    }
    Ok(result)
}

/// Applies `actions` to `env` (already at `result`'s first observation) until they run out or the
/// episode ends, recording each step.
pub(crate) fn play(
    env: &mut dyn Env,
    mut result: ReplayResult,
    actions: &[Vec<f32>],
) -> Result<ReplayResult, EnvError> {
    for (t, action) in actions.iter().enumerate() {
        let step = env.step(action).map_err(|e| at_step(e, t))?;
        if result.record(step, t, actions.len()) {
            break;
        }
    }
    Ok(result)
}

/// [`crate::EnvFamily::replay`] of a MuJoCo family: `init` is required, `{"qpos": [...],
/// "qvel": [...]}`.
pub fn replay_mujoco_init(
    env: &mut MujocoEnv,
    family: &str,
    task: usize,
    init: Option<&str>,
    actions: &[Vec<f32>],
) -> Result<ReplayResult, EnvError> {
    #[derive(Deserialize)]
    struct Init {
        qpos: Vec<f64>,
        qvel: Vec<f64>,
    }
    let Some(text) = init else {
        return Err(EnvError::ReplayInit {
            message: format!("--init is required for {family} (its initial qpos and qvel)"),
        });
    };
    let init: Init = serde_json::from_str(text).map_err(|e| EnvError::ReplayInit {
        message: format!("expected {{\"qpos\": [...], \"qvel\": [...]}}: {e}"),
    })?;
    replay_env(env, family, task, &init.qpos, &init.qvel, actions)
}

/// [`crate::EnvFamily::replay`] of a family whose episodes start from the task's deterministic
/// reset state (point robot, Meta-World reach): no `init` is taken.
pub fn replay_from_reset(
    env: &mut dyn Env,
    family: &str,
    task: usize,
    init: Option<&str>,
    actions: &[Vec<f32>],
) -> Result<ReplayResult, EnvError> {
    if init.is_some() {
        return Err(EnvError::ReplayInit {
            message: format!(
                "{family} episodes start from the task's reset state (no initial state is taken)"
            ),
        });
    }
    let first = env.reset(0);
    play(env, ReplayResult::start(family, task, first, actions.len()), actions)
}

/// Adds the step index to an action error, so that a bad action in a long file can be found.
fn at_step(e: EnvError, t: usize) -> EnvError {
    match e {
        EnvError::ActionDim { env, got, expected } => {
            EnvError::ActionDim { env: format!("{env} (step {t})"), got, expected }
        }
        EnvError::NonFiniteAction { env, index, value } => {
            EnvError::NonFiniteAction { env: format!("{env} (step {t})"), index, value }
        }
        EnvError::ActionTooLarge { env, index, value, limit } => {
            EnvError::ActionTooLarge { env: format!("{env} (step {t})"), index, value, limit }
        }
        other => other,
    }
}
