//! Scripted policies of the families that have them (point robot, Meta-World reach) and a
//! deterministic writer for their datasets.
//!
//! Three policies of decreasing quality ([`Mode`]): `expert` heads straight for the goal,
//! `medium` heads for a goal misremembered once per episode, `random` moves uniformly at random
//! ([`ScriptedFamily::policy_description`] gives each family's exact formulas).
//! [`collect`] writes, for every task `i` and mode `m`, the main dataset D_i
//! (`{env}-{i}-{m}.safetensors`) and the prompt set P_i (`{env}-{i}-prompt-{m}.safetensors`) in
//! the native format, plus a `dataset.json` card.
//!
//! Every episode draws its randomness from its own ChaCha8 generator keyed by
//! `(seed, task, mode, set, episode)`, so the data does not depend on the order in which episodes
//! are generated, on thread count, or on which other tasks and modes are collected in the same run.
//! `docs/point-robot.md` and `docs/metaworld-reach.md` describe the policies and the file layout.

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc;

use pdt_data::native::{
    self, CardFile, CardTask, DatasetCard, FileMeta, ReturnStats, CARD_FILE_NAME, CARD_FORMAT_NAME,
    FORMAT_VERSION,
};
use pdt_data::{DataError, TaskDataset, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::dial::{self, Dial, DialExpert, DialFamily};
use crate::metaworld_reach::{self as reach, MetaWorldReach, MetaWorldReachFamily};
use crate::mujoco_env::standard_normal;
use crate::point_robot::{self, PointRobot, ACT_DIM, ENV_NAME, MAX_SPEED, NUM_TASKS, OBS_DIM};
use crate::{Env, EnvError, EnvFamily, StepResult};

/// Standard deviation of the expert's per-coordinate action noise.
pub const EXPERT_ACTION_NOISE: f64 = 0.01;
/// Standard deviation of the medium policy's per-episode, per-coordinate goal error.
pub const MEDIUM_GOAL_NOISE: f64 = 0.5;
/// Standard deviation of the medium policy's per-coordinate action noise.
pub const MEDIUM_ACTION_NOISE: f64 = 0.05;

/// Meta-World reach: standard deviation of the expert's (and medium policy's) action noise on
/// every dimension, Meta-World's test-harness model `a ~ N(a, (pct * 2)^2)` at pct 0.1, under which
/// Meta-World's own tests require reach's expert to succeed (spec §3: measured 100 % ever-success).
pub const REACH_ACTION_NOISE: f64 = 0.2;
/// Meta-World reach: standard deviation (m) of the medium policy's per-coordinate goal error,
/// drawn once per episode: it settles about 0.17 m from the goal (outside the 0.05 m success
/// radius), which earns about half the expert's return (measured over the paper's 20 tasks, 200
/// episodes each: medium 2,629, expert 4,826, random 777; medium succeeds in 11 % of episodes).
pub const REACH_MEDIUM_GOAL_NOISE: f64 = 0.1;

/// Dial: the expert's per-episode DART noise amounts (the original collector's, spec §3.2), drawn
/// uniformly; the noise on joint j is N(0, (|c_low[j]| amount)^2), plus U(0, 0.1) on joint 1's
/// standard deviation, redrawn every 1 or 2 steps (drawn per episode).
pub const DIAL_DART_AMOUNTS: [f64; 3] = [0.0, 0.2, 0.3];
/// Dial: standard deviation (rad) of the medium policy's per-episode error on each arm joint of
/// its target pose (it then settles near, not at, the key: see `docs/dial.md` for its measured
/// success rate).
pub const DIAL_MEDIUM_TARGET_NOISE: f64 = 0.15;

/// A family with scripted policies.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScriptedFamily {
    #[default]
    PointRobot,
    MetaWorldReach,
    Dial,
}

impl ScriptedFamily {
    /// The family of `name` (as [`crate::family`] spells it), if it has scripted policies.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            point_robot::ENV_NAME => Some(Self::PointRobot),
            reach::ENV_NAME => Some(Self::MetaWorldReach),
            dial::ENV_NAME => Some(Self::Dial),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::PointRobot => ENV_NAME,
            Self::MetaWorldReach => reach::ENV_NAME,
            Self::Dial => dial::ENV_NAME,
        }
    }

    fn num_tasks(self) -> usize {
        match self {
            Self::PointRobot => NUM_TASKS,
            Self::MetaWorldReach => reach::NUM_TASKS,
            Self::Dial => dial::NUM_TASKS,
        }
    }

    fn dims(self) -> (usize, usize) {
        match self {
            Self::PointRobot => (OBS_DIM, ACT_DIM),
            Self::MetaWorldReach => (reach::OBS_DIM, reach::ACT_DIM),
            Self::Dial => (dial::OBS_DIM, dial::ACT_DIM),
        }
    }

    /// The tasks collected by default: every point-robot goal; the 20 reach tasks of the paper's
    /// split (1..=20; the family's other 30 tasks are in no split); the 10 digits of Dial.
    pub fn default_tasks(self) -> Vec<usize> {
        match self {
            Self::PointRobot => (0..NUM_TASKS).collect(),
            Self::MetaWorldReach => {
                let mut t: Vec<usize> =
                    reach::TRAIN_TASKS.iter().chain(&reach::TEST_TASKS).copied().collect();
                t.sort_unstable();
                t
            }
            Self::Dial => (0..dial::NUM_TASKS).collect(),
        }
    }

    /// Episodes per task in D_i by default: the point robot's 100; reach's and Dial's 200 (the
    /// paper's "200 episodes for each task").
    pub fn default_episodes(self) -> usize {
        match self {
            Self::PointRobot => 100,
            Self::MetaWorldReach | Self::Dial => 200,
        }
    }

    fn params(self, task: usize) -> Result<serde_json::Value, EnvError> {
        match self {
            Self::PointRobot => point_robot::PointRobotFamily::default().task_params(task),
            Self::MetaWorldReach => MetaWorldReachFamily::default().task_params(task),
            Self::Dial => DialFamily.task_params(task),
        }
    }

    /// One-line description of `mode`'s policy in this family, recorded in the dataset card.
    pub fn policy_description(self, mode: Mode) -> &'static str {
        match self {
            Self::PointRobot => mode.description(),
            Self::MetaWorldReach => match mode {
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
            },
            Self::Dial => match mode {
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
            },
        }
    }
}

/// A scripted policy, and the dataset kind it produces (the `mode` in file names).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    Expert,
    Medium,
    Random,
}

impl Mode {
    /// All modes, best first.
    pub const ALL: [Mode; 3] = [Mode::Expert, Mode::Medium, Mode::Random];

    /// The name used in file names and cards.
    pub fn name(self) -> &'static str {
        match self {
            Mode::Expert => "expert",
            Mode::Medium => "medium",
            Mode::Random => "random",
        }
    }

    /// One-line description of the policy, recorded in the dataset card.
    pub fn description(self) -> &'static str {
        match self {
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

    /// Stable number of the mode in RNG keys: adding a mode must not change the others' data.
    fn rng_id(self) -> u32 {
        match self {
            Mode::Expert => 0,
            Mode::Medium => 1,
            Mode::Random => 2,
        }
    }
}

impl fmt::Display for Mode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Mode {
    type Err = CollectError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Mode::ALL.into_iter().find(|m| m.name() == s).ok_or_else(|| {
            CollectError::Config(format!("unknown mode {s:?} (known: expert, medium, random)"))
        })
    }
}

/// Which of a task's two sets an episode belongs to. Part of the RNG key, so P_i's episodes are
/// distinct from D_i's and do not change when `episodes_per_task` does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Set {
    /// The main dataset D_i.
    Dataset,
    /// The prompt set P_i.
    Prompt,
}

impl Set {
    fn rng_id(self) -> u32 {
        match self {
            Set::Dataset => 0,
            Set::Prompt => 1,
        }
    }
}

/// What to collect.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CollectConfig {
    /// Which family (default: the point robot).
    #[serde(default)]
    pub family: ScriptedFamily,
    pub seed: u64,
    /// Episodes in each main dataset D_i.
    pub episodes_per_task: usize,
    /// Episodes in each prompt set P_i.
    pub prompt_episodes: usize,
    pub modes: Vec<Mode>,
    /// Task indices of the family (point robot `0..40`, reach `0..50`).
    pub tasks: Vec<usize>,
    /// Meta-World reach: standard deviation of the expert's and medium policy's Gaussian action
    /// noise ([`REACH_ACTION_NOISE`] by default). 0 gives the deterministic expert, whose episodes
    /// of a task are then all the same (spec §5: "200 copies").
    #[serde(default = "default_reach_noise")]
    pub reach_action_noise: f64,
}

fn default_reach_noise() -> f64 {
    REACH_ACTION_NOISE
}

impl Default for CollectConfig {
    fn default() -> Self {
        Self {
            family: ScriptedFamily::PointRobot,
            seed: 0,
            episodes_per_task: 100,
            prompt_episodes: 5,
            modes: Mode::ALL.to_vec(),
            tasks: (0..NUM_TASKS).collect(),
            reach_action_noise: REACH_ACTION_NOISE,
        }
    }
}

impl CollectConfig {
    /// The defaults of `family`: its default tasks and episodes, every mode, seed 0.
    pub fn for_family(family: ScriptedFamily) -> Self {
        Self {
            family,
            episodes_per_task: family.default_episodes(),
            tasks: family.default_tasks(),
            ..Self::default()
        }
    }

    /// Checks the config before anything is written.
    pub fn validate(&self) -> Result<(), CollectError> {
        let bad = |m: String| Err(CollectError::Config(m));
        if self.episodes_per_task == 0 {
            return bad("episodes_per_task must be at least 1".into());
        }
        if self.prompt_episodes == 0 {
            return bad("prompt_episodes must be at least 1".into());
        }
        if !(self.reach_action_noise.is_finite() && (0.0..=10.0).contains(&self.reach_action_noise))
        {
            return bad(format!(
                "reach_action_noise must be a standard deviation between 0 and 10, got {}",
                self.reach_action_noise
            ));
        }
        if self.modes.is_empty() {
            return bad("no modes given".into());
        }
        if self.tasks.is_empty() {
            return bad("no tasks given".into());
        }
        let n = self.family.num_tasks();
        if let Some(&t) = self.tasks.iter().find(|&&t| t >= n) {
            return Err(EnvError::UnknownTask { env: self.family.name().into(), task: t, n }.into());
        }
        // A duplicate would write the same files twice and list them twice in the card.
        for (i, t) in self.tasks.iter().enumerate() {
            if self.tasks[..i].contains(t) {
                return bad(format!("task {t} is listed twice"));
            }
        }
        for (i, m) in self.modes.iter().enumerate() {
            if self.modes[..i].contains(m) {
                return bad(format!("mode {m} is listed twice"));
            }
        }
        Ok(())
    }
}

/// Return statistics of one (task, mode).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskModeSummary {
    pub task: usize,
    pub mode: Mode,
    /// Undiscounted returns of D_i (population std).
    pub dataset: ReturnStats,
    /// Undiscounted returns of P_i.
    pub prompts: ReturnStats,
    pub dataset_file: PathBuf,
    pub prompt_file: PathBuf,
    /// Fraction of D_i's episodes in which the task counted as solved at some step (Meta-World's
    /// `success`); `None` for families without a success criterion.
    pub success_rate: Option<f64>,
}

/// What [`collect`] wrote.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CollectSummary {
    /// One entry per (task, mode), tasks in config order, modes in config order within a task.
    pub entries: Vec<TaskModeSummary>,
    /// Path of the `dataset.json` card.
    pub card: PathBuf,
}

impl CollectSummary {
    /// The entry of `(task, mode)`, if it was collected.
    pub fn get(&self, task: usize, mode: Mode) -> Option<&TaskModeSummary> {
        self.entries.iter().find(|e| e.task == task && e.mode == mode)
    }

    /// Mean over `tasks` of the per-task mean D_i return of `mode`; `None` if any of those tasks
    /// was not collected in that mode, or `tasks` is empty.
    pub fn mean_return(&self, mode: Mode, tasks: &[usize]) -> Option<f64> {
        if tasks.is_empty() {
            return None;
        }
        let mut sum = 0.0;
        for &t in tasks {
            sum += self.get(t, mode)?.dataset.mean;
        }
        Some(sum / tasks.len() as f64)
    }
}

#[derive(Debug, thiserror::Error)]
pub enum CollectError {
    #[error("invalid collection config: {0}")]
    Config(String),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error("cannot create the output directory {}", path.display())]
    CreateDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Writing a dataset file or the card failed; `path` is the file.
    #[error("cannot write {}: {source}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: DataError,
    },
    /// The file was not written because writing another one failed first.
    #[error("stopped after an earlier error")]
    Stopped,
    /// The generated episodes did not form a valid dataset (a bug here, not a user error).
    #[error("generated data for {env}-{task} ({mode}) is invalid: {source}")]
    Data {
        env: &'static str,
        task: usize,
        mode: Mode,
        #[source]
        source: DataError,
    },
}

/// The RNG of one episode. The 256-bit ChaCha key holds the five parts side by side, so distinct
/// tuples get independent streams with no hashing and no chance of collision.
pub fn episode_rng(seed: u64, task: usize, mode: Mode, set: Set, episode: usize) -> ChaCha8Rng {
    let mut key = [0u8; 32];
    key[0..8].copy_from_slice(&seed.to_le_bytes());
    key[8..16].copy_from_slice(&(task as u64).to_le_bytes());
    key[16..20].copy_from_slice(&mode.rng_id().to_le_bytes());
    key[20..24].copy_from_slice(&set.rng_id().to_le_bytes());
    key[24..32].copy_from_slice(&(episode as u64).to_le_bytes());
    ChaCha8Rng::from_seed(key)
}

fn normal(rng: &mut ChaCha8Rng, std: f64) -> f32 {
    (std * standard_normal(rng)) as f32
}

/// The arrays of one episode as it is played, for [`Trajectory::new`].
struct EpisodeLog {
    obs_dim: usize,
    act_dim: usize,
    observations: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    terminated: Vec<bool>,
    truncated: Vec<bool>,
}

impl EpisodeLog {
    fn new(obs_dim: usize, act_dim: usize, horizon: usize) -> Self {
        Self {
            obs_dim,
            act_dim,
            observations: Vec::with_capacity(horizon * obs_dim),
            actions: Vec::with_capacity(horizon * act_dim),
            rewards: Vec::with_capacity(horizon),
            terminated: Vec::with_capacity(horizon),
            truncated: Vec::with_capacity(horizon),
        }
    }

    /// Records `action`, taken at observation `obs`, and its step; returns whether the episode
    /// ended there.
    fn record(&mut self, obs: &[f32], action: &[f32], step: &StepResult) -> bool {
        self.observations.extend_from_slice(obs);
        self.actions.extend_from_slice(action);
        self.rewards.push(step.reward);
        self.terminated.push(step.terminated);
        self.truncated.push(step.truncated);
        step.terminated || step.truncated
    }

    fn finish(self) -> Result<Trajectory, DataError> {
        let Self { obs_dim, act_dim, observations, actions, rewards, terminated, truncated } = self;
        Trajectory::new(obs_dim, act_dim, observations, actions, rewards, terminated, truncated)
    }
}

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
    let traj = log.finish().map_err(|source| CollectError::Data {
        env: reach::ENV_NAME,
        task,
        mode,
        source,
    })?;
    Ok((traj, succeeded))
}

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
    let traj = log.finish().map_err(|source| CollectError::Data {
        env: dial::ENV_NAME,
        task,
        mode,
        source,
    })?;
    Ok((traj, succeeded))
}

/// Generates `episodes` point-robot episodes of `(task, mode)` for one set.
pub fn generate(
    seed: u64,
    task: usize,
    mode: Mode,
    set: Set,
    episodes: usize,
) -> Result<TaskDataset, CollectError> {
    let cfg = CollectConfig { seed, ..CollectConfig::default() };
    Ok(generate_for(&cfg, task, mode, set, episodes)?.0)
}

/// Generates `episodes` episodes of `(task, mode)` of `cfg`'s family with its seed (and noise) for
/// one set; also returns the fraction of episodes that succeeded (`None` for a family without a
/// success criterion).
pub fn generate_for(
    cfg: &CollectConfig,
    task: usize,
    mode: Mode,
    set: Set,
    episodes: usize,
) -> Result<(TaskDataset, Option<f64>), CollectError> {
    let (family, seed) = (cfg.family, cfg.seed);
    let env = family.name();
    let (trajectories, success) = match family {
        ScriptedFamily::PointRobot => {
            let t = (0..episodes)
                .map(|e| run_episode(task, mode, &mut episode_rng(seed, task, mode, set, e)))
                .collect::<Result<Vec<_>, _>>()?;
            (t, None)
        }
        ScriptedFamily::MetaWorldReach => {
            // One simulator for the whole set: every reset restores the same start state, so the
            // episodes do not depend on what ran before them (tests/metaworld_parity.rs).
            let mut sim = MetaWorldReachFamily::default().make_env(task)?;
            let mut t = Vec::with_capacity(episodes);
            let mut wins = 0usize;
            for e in 0..episodes {
                let mut rng = episode_rng(seed, task, mode, set, e);
                let noise = cfg.reach_action_noise;
                let (traj, ok) = run_reach_episode(&mut sim, task, mode, noise, &mut rng)?;
                wins += usize::from(ok);
                t.push(traj);
            }
            (t, Some(wins as f64 / episodes.max(1) as f64))
        }
        ScriptedFamily::Dial => {
            // One simulator for the whole set: every episode starts with a full reset.
            let mut sim = DialFamily.make_env(task)?;
            let mut t = Vec::with_capacity(episodes);
            let mut wins = 0usize;
            for e in 0..episodes {
                let mut rng = episode_rng(seed, task, mode, set, e);
                let (traj, ok) = run_dial_episode(&mut sim, mode, &mut rng)?;
                wins += usize::from(ok);
                t.push(traj);
            }
            (t, Some(wins as f64 / episodes.max(1) as f64))
        }
    };
    let ds = TaskDataset::new(trajectories).map_err(|source| CollectError::Data {
        env,
        task,
        mode,
        source,
    })?;
    Ok((ds, success))
}

/// Writes the datasets of `cfg` into `out_dir` (created if missing) and a `dataset.json` card
/// describing exactly what this call wrote (an existing card is replaced). `progress(done, total)`
/// is called after each (task, mode) is written, with `total = tasks x modes`.
///
/// Same `cfg` gives byte-identical data; the files of each (task, mode) do not depend on the other
/// tasks and modes in `cfg`.
pub fn collect(
    cfg: &CollectConfig,
    out_dir: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<CollectSummary, CollectError> {
    cfg.validate()?;
    std::fs::create_dir_all(out_dir)
        .map_err(|source| CollectError::CreateDir { path: out_dir.to_path_buf(), source })?;
    let family = cfg.family;
    let total = cfg.tasks.len() * cfg.modes.len();
    // One job per file, in card order: pair p = task position * modes + mode position, and its
    // jobs 2p (D_i) and 2p + 1 (P_i).
    let jobs: Vec<(usize, Mode, Set, usize)> = cfg
        .tasks
        .iter()
        .flat_map(|&task| {
            cfg.modes.iter().flat_map(move |&mode| {
                [
                    (task, mode, Set::Dataset, cfg.episodes_per_task),
                    (task, mode, Set::Prompt, cfg.prompt_episodes),
                ]
            })
        })
        .collect();
    let mut results = run_jobs(cfg, &jobs, out_dir, total, progress);
    // Report the real failure, not a job skipped because of it.
    let failure =
        results.iter().position(|r| matches!(r, Err(e) if !matches!(e, CollectError::Stopped)));
    if let Some(i) = failure {
        results.swap_remove(i)?;
    }
    let mut results = results.into_iter();

    let mut entries = Vec::with_capacity(total);
    let mut card_tasks = Vec::with_capacity(cfg.tasks.len());
    for &task in &cfg.tasks {
        let mut files = Vec::with_capacity(2 * cfg.modes.len());
        for &mode in &cfg.modes {
            // `run_jobs` returns one result per job, so both are present, and none is an error.
            let (main, dataset_file, success_rate) =
                results.next().ok_or(CollectError::Stopped)??;
            let (prompt, prompt_file, _) = results.next().ok_or(CollectError::Stopped)??;
            entries.push(TaskModeSummary {
                task,
                mode,
                dataset: main.returns,
                prompts: prompt.returns,
                dataset_file,
                prompt_file,
                success_rate,
            });
            files.push(main);
            files.push(prompt);
        }
        card_tasks.push(CardTask { index: task, params: family.params(task)?, files });
    }
    let (obs_dim, act_dim) = family.dims();
    let card = DatasetCard {
        format: CARD_FORMAT_NAME.to_owned(),
        format_version: FORMAT_VERSION.to_owned(),
        env: family.name().to_owned(),
        obs_dim,
        act_dim,
        tasks: card_tasks,
        generator: generator_info(cfg),
    };
    native::write_card(out_dir, &card)
        .map_err(|source| CollectError::Write { path: out_dir.join(CARD_FILE_NAME), source })?;
    Ok(CollectSummary { entries, card: out_dir.join(CARD_FILE_NAME) })
}

/// Threads writing files. Writing is dominated by each file's fsync, which waits on the disk
/// rather than using a CPU, so more threads than cores still help; 240 files take ~1.5 s on one
/// thread. The data does not depend on this number (each file has its own RNGs).
const WRITE_THREADS: usize = 16;

type JobResult = Result<(CardFile, PathBuf, Option<f64>), CollectError>;

/// Generates and writes every job on [`WRITE_THREADS`] threads; returns the results in job order.
/// After the first failure no new job starts (its result is [`CollectError::Stopped`]).
/// `progress(done, total)` runs on this thread each time both files of a (task, mode) pair (jobs
/// `2p` and `2p + 1`) are written.
fn run_jobs(
    cfg: &CollectConfig,
    jobs: &[(usize, Mode, Set, usize)],
    out_dir: &Path,
    total_pairs: usize,
    progress: &mut dyn FnMut(usize, usize),
) -> Vec<JobResult> {
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let mut results: Vec<JobResult> = (0..jobs.len()).map(|_| Err(CollectError::Stopped)).collect();
    std::thread::scope(|scope| {
        let (tx, rx) = mpsc::channel::<usize>();
        let workers: Vec<_> = (0..WRITE_THREADS.min(jobs.len()))
            .map(|_| {
                let tx = tx.clone();
                let (next, failed) = (&next, &failed);
                scope.spawn(move || {
                    let mut done = Vec::new();
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let Some(&(task, mode, set, episodes)) = jobs.get(i) else { break };
                        if failed.load(Ordering::Relaxed) {
                            break;
                        }
                        let result = write_set(cfg, task, mode, set, episodes, out_dir);
                        if result.is_err() {
                            failed.store(true, Ordering::Relaxed);
                        } else {
                            // The receiver lives until every worker is joined; a send error
                            // would only mean nobody listens for progress any more.
                            let _ = tx.send(i);
                        }
                        done.push((i, result));
                    }
                    done
                })
            })
            .collect();
        // Only the workers' clones may keep the channel open, so `recv` ends when they finish.
        drop(tx);
        let mut pair_files = vec![0u8; total_pairs];
        let mut pairs_done = 0;
        for i in rx {
            let pair = i / 2;
            pair_files[pair] += 1;
            if pair_files[pair] == 2 {
                pairs_done += 1;
                progress(pairs_done, total_pairs);
            }
        }
        for worker in workers {
            match worker.join() {
                Ok(done) => {
                    for (i, result) in done {
                        results[i] = result;
                    }
                }
                // A worker panicked (a bug): re-raise it here rather than report a fake error.
                Err(panic) => std::panic::resume_unwind(panic),
            }
        }
    });
    results
}

/// Generates and writes one file; returns its card entry, path and success rate.
fn write_set(
    cfg: &CollectConfig,
    task: usize,
    mode: Mode,
    set: Set,
    episodes: usize,
    out_dir: &Path,
) -> JobResult {
    let file_mode = match set {
        Set::Dataset => mode.name().to_owned(),
        Set::Prompt => format!("prompt-{}", mode.name()),
    };
    let env = cfg.family.name();
    let name =
        format!("{}.{}", native::task_file_stem(env, task, &file_mode), native::FILE_EXTENSION);
    let path = out_dir.join(&name);
    let (ds, success) = generate_for(cfg, task, mode, set, episodes)?;
    let meta = FileMeta::new(env, task, file_mode.clone());
    native::write_task_dataset(&path, &ds, &meta)
        .map_err(|source| CollectError::Write { path: path.clone(), source })?;
    Ok((CardFile::describe(name, file_mode, &ds), path, success))
}

/// The card's `generator` entry: enough to regenerate the data.
fn generator_info(cfg: &CollectConfig) -> serde_json::Value {
    let policies: serde_json::Map<String, serde_json::Value> = cfg
        .modes
        .iter()
        .map(|m| (m.name().to_owned(), serde_json::Value::from(cfg.family.policy_description(*m))))
        .collect();
    let mut info = serde_json::json!({
        "name": "pdt-envs collect_scripted",
        "version": env!("CARGO_PKG_VERSION"),
        "seed": cfg.seed,
        "episodes_per_task": cfg.episodes_per_task,
        "prompt_episodes": cfg.prompt_episodes,
        "policies": policies,
        "rng": "ChaCha8, one generator per episode keyed by (seed, task, mode, set, episode); \
                normal noise by Box-Muller",
    });
    if cfg.family == ScriptedFamily::MetaWorldReach {
        info["action_noise_std"] = cfg.reach_action_noise.into();
    }
    info
}
