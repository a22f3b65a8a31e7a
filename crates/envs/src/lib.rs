//! Environments behind one small [`Env`] trait, grouped into task families ([`EnvFamily`]) with
//! their task parameters, train/test splits and the reference's per-environment constants
//! ([`EnvPreset`]). No tensor framework here.
//!
//! A family also answers what the front ends (CLI, Python, `reproduce`, report, RL, bench) would
//! otherwise decide by its name: its action bounds, success rule, how its datasets are collected
//! (scripted policies, or an RL agent with the preset of `configs/collect/<family>.toml`), the RL
//! agent's task features and body symmetries, its dataset quality bar, and replay.
//! `docs/adding-a-family.md` lists what a new family adds, all of it in this crate and `configs/`.

pub mod ant_dir;
pub mod bench;
pub mod cheetah;
pub mod collect_policy;
pub mod collect_scripted;
pub mod dial;
pub mod metaworld_reach;
pub mod mujoco_env;
pub mod point_robot;
pub mod render;
pub mod replay;
pub mod rollout;
pub mod suite;
pub mod vec_env;
pub mod worker;

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
    /// Data said to be of a family whose observation or action size differs ([`check_dims`]).
    #[error(
        "data of obs_dim {obs_dim} and act_dim {act_dim} cannot be {env}'s: {env} has obs_dim \
         {expected_obs} and act_dim {expected_act}"
    )]
    WrongDims {
        env: String,
        obs_dim: usize,
        act_dim: usize,
        expected_obs: usize,
        expected_act: usize,
    },
    #[error("unknown split `{split}` of {env} (known: {known})")]
    UnknownSplit { env: String, split: String, known: String },
    #[error("{env}: {message}")]
    Simulation { env: String, message: String },
    /// A simulator state given from outside (e.g. a replay's initial `qpos`/`qvel`) is unusable.
    #[error("{env}: invalid state: {message}")]
    BadState { env: String, message: String },
    /// The family lacks a capability a caller asked for (e.g. replay, or RL task features).
    #[error("{env} has no {what}")]
    Unsupported { env: String, what: &'static str },
    /// A replay's initial state (`promptdt env replay --init`) is missing, unwanted or unreadable.
    #[error("{message}")]
    ReplayInit { message: String },
    /// A Python worker's environment or the worker itself failed ([`worker`]): `task` names the
    /// task (`name (task i)`, or the batch's tasks when the whole worker failed), `step` the
    /// episode step (`None`: while making or resetting the environments).
    #[error("{task}{}: {message}", at_step(*.step))]
    Worker { task: String, step: Option<usize>, message: String },
    /// A front end asked the rollouts to stop (`rollout::Watch`, its Ctrl-C).
    #[error("stopped on request before the episodes ended")]
    Interrupted,
    /// A task suite file ([`suite`]) that cannot be read or has a bad field.
    #[error(transparent)]
    Suite(#[from] suite::SuiteError),
}

/// `, step N` for [`EnvError::Worker`]'s message, where a step is known.
fn at_step(step: Option<usize>) -> String {
    step.map(|s| format!(", step {s}")).unwrap_or_default()
}

impl EnvError {
    /// `Ok` for a task index of a family of `n` tasks, else [`EnvError::UnknownTask`].
    pub fn check_task(env: &str, task: usize, n: usize) -> Result<(), EnvError> {
        match task < n {
            true => Ok(()),
            false => Err(EnvError::UnknownTask { env: env.into(), task, n }),
        }
    }

    /// [`EnvError::UnknownSplit`] for `split` of `env`, naming its `known` splits.
    pub fn unknown_split(env: &str, split: &str, known: &[&str]) -> EnvError {
        EnvError::UnknownSplit { env: env.into(), split: split.into(), known: known.join(", ") }
    }
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

    /// The current state as a renderer draws it, with the family's camera ([`render`]); families
    /// that cannot be drawn keep this default.
    fn view(&mut self) -> Result<render::View<'_>, EnvError> {
        Err(EnvError::Unsupported { env: "this environment".to_owned(), what: "rendering" })
    }
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

/// The closed box an action lies in, per dimension (`low[i] <= a[i] <= high[i]`): what the
/// Python package's gymnasium spaces and Minari exports declare. Values outside are clamped (the
/// MuJoCo families' motors, Dial's controller) or clipped (the point robot's speed) by the env.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionBounds {
    pub low: Vec<f32>,
    pub high: Vec<f32>,
}

impl ActionBounds {
    /// `[-bound, bound]` on each of `act_dim` dimensions.
    pub fn symmetric(bound: f32, act_dim: usize) -> Self {
        Self { low: vec![-bound; act_dim], high: vec![bound; act_dim] }
    }
}

/// The dataset quality bar of a family (`promptdt report --datasets`), besides the bars every
/// family has (medium between random and expert; expert success where there is a success rule).
#[derive(Debug, Clone, PartialEq)]
pub enum DatasetBar {
    /// Per task against the reference's expert return: ours >= ref - tolerance * |ref| on every
    /// one of the family's tasks.
    Reference { tolerance: f64, name: &'static str },
    /// On the mean expert return over the family's tasks.
    Mean { min: f64, name: &'static str },
}

/// A symmetry of the body (a reflection or a half turn) under which the family's dynamics are
/// the same: an RL agent can act in the mirrored world (`pdt_rl::agent::Mirror`). Each map is a
/// signed permutation `out[i] = sign[i] * x[index[i]]` and its own inverse.
#[derive(Debug, Clone, PartialEq)]
pub struct BodySymmetry {
    pub name: &'static str,
    pub observation: ant_dir::SignedPerm,
    pub action: ant_dir::SignedPerm,
    /// Signs of the task feature ([`EnvFamily::task_features`]) under the symmetry.
    pub task_feature_sign: Vec<f64>,
}

/// A task family: its tasks, splits and constants, a factory for its environments, and the
/// knowledge the front ends need about it (module docs).
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

    /// The environments of a batch of episodes, environment `i` one of task `tasks[i]`; `threads`
    /// is how many threads may step those that live in this process. By default each is
    /// [`Self::make`]'s, on a [`vec_env::VecEnv`]'s thread pool. A family whose environments live
    /// elsewhere (a user's gymnasium environments in a Python worker: [`worker`]) makes them all
    /// at once behind one [`vec_env::Backend`], so the evaluations, which make their environments
    /// here, step them with one message per vector step and never know the difference.
    fn make_batch(&self, tasks: &[usize], threads: usize) -> Result<vec_env::VecEnv, EnvError> {
        let envs = tasks.iter().map(|&t| self.make(t)).collect::<Result<Vec<_>, _>>()?;
        Ok(vec_env::VecEnv::new(envs, threads))
    }

    /// Environment steps per second of the family's simulated time (gymnasium's `render_fps`, what
    /// a video of its episodes plays at): 1 / (frame skip x the simulator's timestep).
    fn render_fps(&self) -> u32;

    /// The box actions lie in.
    fn action_bounds(&self) -> ActionBounds;

    /// The reward at or above which a step solved its task, for families whose success can be
    /// read off their recorded rewards; `None` for families without a success criterion.
    fn success_reward(&self) -> Option<f32> {
        None
    }

    /// The family's scripted policies, if its datasets are collected by them
    /// ([`collect_scripted`]); `None`: they are collected from an RL agent ([`Self::rl_preset`]).
    fn scripted(&self) -> Option<collect_scripted::ScriptedFamily> {
        None
    }

    /// The RL agent preset (`configs/collect/<family>.toml`, TOML text read by `pdt-rl`), for
    /// families an agent can be trained on.
    fn rl_preset(&self) -> Option<&'static str> {
        None
    }

    /// The task's features the RL agent is conditioned on (e.g. `[velocity]`), all tasks' of the
    /// same length.
    fn task_features(&self, _task: usize) -> Result<Vec<f32>, EnvError> {
        Err(EnvError::Unsupported { env: self.name().to_owned(), what: "RL task features" })
    }

    /// Body symmetries an RL agent may act under (none by default).
    fn symmetries(&self) -> Vec<BodySymmetry> {
        Vec::new()
    }

    /// The family's own dataset quality bar, if it has one.
    fn dataset_bar(&self) -> Option<DatasetBar> {
        None
    }

    /// The task's own target return G*, where it differs from the family's
    /// ([`EnvPreset::target_return`]); `None` for the built-in families.
    fn task_target_return(&self, _task: usize) -> Option<f32> {
        None
    }

    /// `(expert_return, random_return)` normalising the task's scores, where the family declares
    /// them (a suite's per-task `expert_return`/`random_return`); `None` for the built-in
    /// families, whose reference returns come from the reference release's data.
    fn reference_returns(&self, _task: usize) -> Option<(f64, f64)> {
        None
    }

    /// The family as a task suite read from a file ([`suite::SuiteFamily`]), if it is one: what a
    /// run directory keeps a copy of.
    fn as_suite(&self) -> Option<&suite::SuiteFamily> {
        None
    }

    /// Replays `actions` on `task` from the start `init` (JSON text, the family's own format:
    /// `promptdt env replay --init`; `None`: none given) until they run out or the episode ends.
    fn replay(
        &self,
        _task: usize,
        _init: Option<&str>,
        _actions: &[Vec<f32>],
    ) -> Result<ReplayResult, EnvError> {
        Err(EnvError::Unsupported { env: self.name().to_owned(), what: "replay" })
    }
}

/// The numeric task parameter `key` of `params` (a family's [`EnvFamily::task_params`]), as f32.
fn numeric_param(
    env: &str,
    task: usize,
    params: &serde_json::Value,
    key: &str,
) -> Result<f32, EnvError> {
    params.get(key).and_then(serde_json::Value::as_f64).map(|v| v as f32).ok_or_else(|| {
        EnvError::Simulation {
            env: env.to_owned(),
            message: format!("task {task}: no numeric parameter `{key}`"),
        }
    })
}

/// Names of the families [`family`] knows.
pub const FAMILY_NAMES: [&str; 6] =
    ["point_robot", "cheetah_dir", "cheetah_vel", "ant_dir", "metaworld_reach", "dial"];

/// [`EnvFamily::success_reward`] of the family named `family`; `None` also for an unknown name.
pub fn success_reward(family: &str) -> Option<f32> {
    self::family(family).ok()?.success_reward()
}

/// Looks up a family by name, or reads a task suite file: a name ending in `.toml` is the path
/// of one ([`suite::is_suite_path`]; a relative path is taken from the working directory).
pub fn family(name: &str) -> Result<Box<dyn EnvFamily>, EnvError> {
    if suite::is_suite_path(name) {
        return Ok(Box::new(suite::SuiteFamily::load(std::path::Path::new(name))?));
    }
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
        other => Err(EnvError::UnknownEnv(
            other.to_string(),
            format!(
                "{}, or the path of a task suite file ending in .toml",
                FAMILY_NAMES.join(", ")
            ),
        )),
    }
}

/// The family of a run whose configuration names `name`: for a task suite whose run keeps a copy
/// of it at `copy` (a run directory's `suite.toml`), the suite as trained
/// ([`suite::SuiteFamily::as_trained`]); otherwise [`family`]`(name)`.
pub fn family_of_run(name: &str, copy: &std::path::Path) -> Result<Box<dyn EnvFamily>, EnvError> {
    if suite::is_suite_path(name) && copy.exists() {
        return Ok(Box::new(suite::SuiteFamily::as_trained(std::path::Path::new(name), copy)?));
    }
    family(name)
}

/// Checks that data of `obs_dim`-sized observations and `act_dim`-sized actions can be the family
/// `name`'s (a dataset written or imported under its name): an unknown family or other sizes are
/// refused, each error naming both.
pub fn check_dims(name: &str, obs_dim: usize, act_dim: usize) -> Result<(), EnvError> {
    let fam = family(name)?;
    let preset = fam.preset();
    if (obs_dim, act_dim) == (preset.obs_dim, preset.act_dim) {
        Ok(())
    } else {
        Err(EnvError::WrongDims {
            env: fam.name().to_owned(),
            obs_dim,
            act_dim,
            expected_obs: preset.obs_dim,
            expected_act: preset.act_dim,
        })
    }
}

/// The concrete environment of a MuJoCo family's task (Ant-Dir with the reference's contact cost).
pub fn make_mujoco_env(family: &str, task: usize) -> Result<mujoco_env::MujocoEnv, EnvError> {
    match family {
        "cheetah_dir" => cheetah::CheetahDirFamily::default().make_env(task),
        "cheetah_vel" => cheetah::CheetahVelFamily::default().make_env(task),
        "ant_dir" => ant_dir::AntDirFamily::default().make_env(task),
        other => Err(EnvError::UnknownEnv(other.to_string(), replay::REPLAY_FAMILIES.join(", "))),
    }
}
