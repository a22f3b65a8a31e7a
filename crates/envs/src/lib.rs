//! Environments behind one small [`Env`] trait, grouped into task families ([`EnvFamily`]) with
//! their task parameters, train/test splits and the reference's per-environment constants
//! ([`EnvPreset`]). No tensor framework here.

pub mod ant_dir;
pub mod bench;
pub mod cheetah;
pub mod collect_scripted;
pub mod dial;
pub mod metaworld_reach;
pub mod mujoco_env;
pub mod point_robot;
pub mod replay;
pub mod rollout;
pub mod vec_env;

pub use replay::{replay, ReplayResult};

use serde::{Deserialize, Serialize};

/// What one environment step returns.
#[derive(Debug, Clone, PartialEq)]
pub struct StepResult {
    /// Observation after the step.
    pub obs: Vec<f32>,
    pub reward: f32,
    /// The MDP ended (e.g. the robot fell): no bootstrapping past this step.
    pub terminated: bool,
    /// The time limit cut the episode; the MDP itself did not end.
    pub truncated: bool,
    /// Whether the task counts as solved after this step (Meta-World's `info["success"]`); `None`
    /// for families without a success criterion.
    pub success: Option<bool>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum EnvError {
    #[error("{env}: action has {got} values, expected {expected}")]
    ActionDim { env: String, got: usize, expected: usize },
    #[error("{env}: action[{index}] is {value}, not a finite number")]
    NonFiniteAction { env: String, index: usize, value: f32 },
    /// A finite action so large that a number computed from it (e.g. a control cost) would not be
    /// finite in f32.
    #[error(
        "{env}: action[{index}] is {value:e}, beyond the largest magnitude accepted ({limit:e}: its \
         control cost would overflow the f32 reward; the motors saturate far below it anyway)"
    )]
    ActionTooLarge { env: String, index: usize, value: f32, limit: f32 },
    #[error("{env}: step called after the episode ended (call reset first)")]
    Finished { env: String },
    #[error("unknown task {task} of {env} (it has tasks 0..{n})")]
    UnknownTask { env: String, task: usize, n: usize },
    #[error("unknown environment `{0}` (known: {1})")]
    UnknownEnv(String, String),
    #[error("unknown split `{split}` of {env} (known: {known})")]
    UnknownSplit { env: String, split: String, known: String },
    #[error("{env}: {message}")]
    Simulation { env: String, message: String },
    /// A simulator state given from outside (e.g. a replay's initial `qpos`/`qvel`) is unusable.
    #[error("{env}: invalid state: {message}")]
    BadState { env: String, message: String },
}

/// One task instance of an environment family.
///
/// `reset` draws any start-state noise from an RNG seeded by `seed`, so an episode is fully
/// determined by (task, seed, actions).
pub trait Env: Send {
    fn obs_dim(&self) -> usize;
    fn act_dim(&self) -> usize;
    /// Time limit: `step` reports `truncated` at this many steps.
    fn horizon(&self) -> usize;
    /// Starts an episode; returns the first observation.
    fn reset(&mut self, seed: u64) -> Vec<f32>;
    /// Applies `action`; errors on a wrong length, a non-finite value, or a finished episode.
    fn step(&mut self, action: &[f32]) -> Result<StepResult, EnvError>;
}

/// The reference's per-environment constants (`promptdt-reference.md` c.4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EnvPreset {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// Evaluation horizon and timestep clip (`max_ep_len`).
    pub horizon: usize,
    /// Return-to-go divisor.
    pub rtg_scale: f32,
    /// Target return G* conditioning evaluation.
    pub target_return: f32,
    /// Prompt segment length H (with J = 1).
    pub prompt_length: usize,
}

/// A task family: its tasks, splits and constants, and a factory for its environments.
pub trait EnvFamily: Send + Sync {
    /// Reference name, used in file names (`cheetah_vel`, `point_robot`).
    fn name(&self) -> &str;
    fn num_tasks(&self) -> usize;
    fn preset(&self) -> EnvPreset;
    /// Names of the predefined train/test splits (the first is the default).
    fn split_names(&self) -> Vec<String>;
    /// `(train, test)` task indices of a named split.
    fn split(&self, name: &str) -> Result<(Vec<usize>, Vec<usize>), EnvError>;
    /// The task's parameters, as recorded in dataset cards (e.g. `{"goal": [x, y]}`).
    fn task_params(&self, task: usize) -> Result<serde_json::Value, EnvError>;
    fn make(&self, task: usize) -> Result<Box<dyn Env>, EnvError>;
}

/// Names of the families [`family`] knows.
pub const FAMILY_NAMES: [&str; 6] =
    ["point_robot", "cheetah_dir", "cheetah_vel", "ant_dir", "metaworld_reach", "dial"];

/// The reward at or above which a step of `family` solved its task, for families whose success
/// can be read off their recorded rewards: Meta-World reach ([`metaworld_reach::SUCCESS_REWARD`])
/// and Dial ([`dial::SUCCESS_REWARD`]).
/// `None` for families without a success criterion.
pub fn success_reward(family: &str) -> Option<f32> {
    match family {
        metaworld_reach::ENV_NAME => Some(metaworld_reach::SUCCESS_REWARD),
        dial::ENV_NAME => Some(dial::SUCCESS_REWARD),
        _ => None,
    }
}

/// Looks up a family by name.
pub fn family(name: &str) -> Result<Box<dyn EnvFamily>, EnvError> {
    match name {
        "point_robot" | "point-robot" => Ok(Box::new(point_robot::PointRobotFamily::default())),
        "cheetah_dir" => Ok(Box::new(cheetah::CheetahDirFamily::default())),
        "cheetah_vel" => Ok(Box::new(cheetah::CheetahVelFamily::default())),
        // The contact cost as the reference computed it (zero): see `ant_dir::ContactCost`.
        "ant_dir" => Ok(Box::new(ant_dir::AntDirFamily::default())),
        // ML1('reach-v2', seed=1) train tasks, goal hidden: see `metaworld_reach`.
        "metaworld_reach" | "metaworld-reach" => {
            Ok(Box::new(metaworld_reach::MetaWorldReachFamily::default()))
        }
        // The reconstructed Jaco pin-pad: see `dial`.
        "dial" => Ok(Box::new(dial::DialFamily)),
        other => Err(EnvError::UnknownEnv(other.to_string(), FAMILY_NAMES.join(", "))),
    }
}
