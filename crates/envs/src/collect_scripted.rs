//! The machinery that collects a scripted family's datasets: RNG keys, files, card, threads.
//!
//! Three policies of decreasing quality ([`Mode`]): `expert` heads straight for the goal,
//! `medium` heads for a goal misremembered once per episode, `random` moves uniformly at random
//! ([`ScriptedFamily::policy_description`] gives each family's exact formulas). Each family owns
//! its policies ([`ScriptedPolicies`], beside its environment: `point_robot.rs`,
//! `metaworld_reach/collect.rs`, `dial/collect.rs`) and hands them out through
//! [`EnvFamily::scripted`]; nothing here names a family.
//! [`collect`] writes, for every task `i` and mode `m`, the main dataset D_i
//! (`{env}-{i}-{m}.safetensors`) and the prompt set P_i (`{env}-{i}-prompt-{m}.safetensors`) in
//! the native format, plus a `dataset.json` card.
//!
//! Every episode draws its randomness from its own ChaCha8 generator keyed by
//! `(seed, task, mode, set, episode)`, so the data does not depend on the order in which episodes
//! are generated, on thread count, or on which other tasks and modes are collected in the same run.
//! `docs/point-robot.md` and `docs/metaworld-reach.md` describe the policies and the file layout.

use pdt_data::mode::{Mode, Set};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc;

use pdt_data::native::{
    self, CardFile, CardTask, DatasetCard, FileMeta, ReturnStats, CARD_FILE_NAME, CARD_FORMAT_NAME,
    FORMAT_VERSION,
};
use pdt_data::{DataError, TaskDataset, Trajectory};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::{EnvError, EnvFamily, StepResult};

/// A family's scripted policies: one implementation per family, in the family's own module, which
/// hands it out through [`EnvFamily::scripted`].
pub trait ScriptedPolicies: Sync {
    /// The family's name (as [`crate::family`] spells it).
    fn name(&self) -> &'static str;
    /// The family the policies act in.
    fn family(&self) -> Box<dyn EnvFamily>;
    /// The tasks collected by default.
    fn default_tasks(&self) -> Vec<usize>;
    /// Episodes per task in D_i by default.
    fn default_episodes(&self) -> usize;
    /// One-line description of `mode`'s policy, recorded in the dataset card.
    fn policy_description(&self, mode: Mode) -> &'static str;
    /// Whether the expert's and medium policy's action noise is set by
    /// [`CollectConfig::reach_action_noise`] (`--action-noise`).
    fn takes_action_noise(&self) -> bool {
        false
    }
    /// That noise's default (a standard deviation); only read where [`Self::takes_action_noise`].
    fn default_action_noise(&self) -> f64 {
        0.0
    }
    /// `episodes` episodes of `(task, mode)` for one set, with `cfg`'s seed (and noise); also the
    /// fraction that succeeded (`None` for a family without a success criterion).
    fn episodes(
        &self,
        cfg: &CollectConfig,
        task: usize,
        mode: Mode,
        set: Set,
        episodes: usize,
    ) -> Result<(Vec<Trajectory>, Option<f64>), CollectError>;
}

/// A family with scripted policies, as its [`EnvFamily::scripted`] hands them out: the handle
/// configs and front ends hold. Compared, printed and serialised by the family's name.
#[derive(Clone, Copy)]
pub struct ScriptedFamily(&'static dyn ScriptedPolicies);

impl ScriptedFamily {
    /// The handle of a family's policies (for its [`EnvFamily::scripted`]).
    pub const fn new(policies: &'static dyn ScriptedPolicies) -> Self {
        Self(policies)
    }

    /// Every family with scripted policies, in [`crate::FAMILY_NAMES`] order.
    pub fn all() -> Vec<Self> {
        crate::FAMILY_NAMES.iter().filter_map(|name| Self::from_name(name)).collect()
    }

    /// The family of `name` (as [`crate::family`] spells it), if it has scripted policies.
    pub fn from_name(name: &str) -> Option<Self> {
        crate::family(name).ok()?.scripted()
    }

    /// The family of `name`; an unknown family, or one collected by an RL agent, is an error
    /// naming the families that have scripted policies.
    pub fn named(name: &str) -> Result<Self, CollectError> {
        Self::from_name(name).ok_or_else(|| {
            let known: Vec<&str> = Self::all().iter().map(|f| f.name()).collect();
            CollectError::Config(format!(
                "`{name}` has no scripted policies (the families that do: {})",
                known.join(", ")
            ))
        })
    }

    /// The family's policies.
    pub fn policies(self) -> &'static dyn ScriptedPolicies {
        self.0
    }

    pub fn name(self) -> &'static str {
        self.0.name()
    }

    fn num_tasks(self) -> usize {
        self.0.family().num_tasks()
    }

    fn dims(self) -> (usize, usize) {
        let p = self.0.family().preset();
        (p.obs_dim, p.act_dim)
    }

    /// The tasks collected by default ([`ScriptedPolicies::default_tasks`]).
    pub fn default_tasks(self) -> Vec<usize> {
        self.0.default_tasks()
    }

    /// Episodes per task in D_i by default ([`ScriptedPolicies::default_episodes`]).
    pub fn default_episodes(self) -> usize {
        self.0.default_episodes()
    }

    fn params(self, task: usize) -> Result<serde_json::Value, EnvError> {
        self.0.family().task_params(task)
    }

    /// One-line description of `mode`'s policy in this family, recorded in the dataset card.
    pub fn policy_description(self, mode: Mode) -> &'static str {
        self.0.policy_description(mode)
    }

    /// Whether `--action-noise` ([`CollectConfig::reach_action_noise`]) applies to this family.
    pub fn takes_action_noise(self) -> bool {
        self.0.takes_action_noise()
    }
}

impl PartialEq for ScriptedFamily {
    fn eq(&self, other: &Self) -> bool {
        self.name() == other.name()
    }
}

impl Eq for ScriptedFamily {}

impl std::fmt::Debug for ScriptedFamily {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("ScriptedFamily").field(&self.name()).finish()
    }
}

impl Serialize for ScriptedFamily {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for ScriptedFamily {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        Self::named(&name).map_err(serde::de::Error::custom)
    }
}

/// What to collect ([`CollectConfig::for_family`] gives a family's defaults).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CollectConfig {
    /// Which family.
    pub family: ScriptedFamily,
    pub seed: u64,
    /// Episodes in each main dataset D_i.
    pub episodes_per_task: usize,
    /// Episodes in each prompt set P_i.
    pub prompt_episodes: usize,
    pub modes: Vec<Mode>,
    /// Task indices of the family (point robot `0..40`, reach `0..50`).
    pub tasks: Vec<usize>,
    /// The expert's and medium policy's Gaussian action noise (a standard deviation), for the
    /// families that take one ([`ScriptedPolicies::takes_action_noise`]: Meta-World reach, whose
    /// default is `metaworld_reach::REACH_ACTION_NOISE`). 0 gives the deterministic expert, whose
    /// episodes of a task are then all the same (spec §5: "200 copies").
    pub reach_action_noise: f64,
    /// A request to stop now (a front end's Ctrl-C), checked before every episode: the call then
    /// returns [`CollectError::Interrupted`]; the files already written are whole (each is
    /// written atomically) and the card is not written. Not a setting: never serialised.
    #[serde(skip)]
    pub interrupt: pdt_base::stop::StopFlag,
    /// Episodes played so far by the call's threads, datasets' and prompt sets' alike (for a
    /// front end's progress: [`collect`]'s own callback only sees whole files). Not a setting:
    /// never serialised.
    #[serde(skip)]
    pub episodes_played: crate::rollout::EpisodeCount,
}

impl CollectConfig {
    /// The defaults of `family`: its default tasks, episodes and action noise, every mode, 5
    /// prompt episodes per set, seed 0.
    pub fn for_family(family: ScriptedFamily) -> Self {
        Self {
            family,
            seed: 0,
            episodes_per_task: family.default_episodes(),
            prompt_episodes: 5,
            modes: Mode::ALL.to_vec(),
            tasks: family.default_tasks(),
            reach_action_noise: family.policies().default_action_noise(),
            interrupt: pdt_base::stop::StopFlag::default(),
            episodes_played: Default::default(),
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

/// `promptdt collect`'s table: per (task, mode) the mean return of D_i and P_i (and the success
/// rate where the family has one); of many tasks (the point robot's 40) every eighth, so the table
/// stays readable. Ends with what was written, without a newline.
impl std::fmt::Display for CollectSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let success = self.entries.iter().any(|e| e.success_rate.is_some());
        write!(f, "{:<6} {:<8} {:>14} {:>14}", "task", "mode", "D_i return", "P_i return")?;
        writeln!(f, "{}", if success { format!(" {:>10}", "success") } else { String::new() })?;
        let mut tasks: Vec<usize> = self.entries.iter().map(|e| e.task).collect();
        tasks.sort_unstable();
        tasks.dedup();
        let many = tasks.len() > 20;
        for e in self.entries.iter().filter(|e| !many || e.task % 8 == 2) {
            let (d, p) = (e.dataset.mean, e.prompts.mean);
            write!(f, "{:<6} {:<8} {d:>14.2} {p:>14.2}", e.task, e.mode.name())?;
            let rate = e.success_rate.map_or(String::new(), |r| format!(" {:>9.1}%", 100.0 * r));
            writeln!(f, "{rate}")?;
        }
        write!(f, "wrote {} datasets and {}", self.entries.len() * 2, self.card.display())
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
    /// A stop was asked for ([`CollectConfig::interrupt`]).
    #[error("collection interrupted: the files written so far are whole, the card was not written; collect again to finish")]
    Interrupted,
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

/// The arrays of one episode as a family's policies play it, for [`Trajectory::new`].
pub(crate) struct EpisodeLog {
    obs_dim: usize,
    act_dim: usize,
    observations: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    terminated: Vec<bool>,
    truncated: Vec<bool>,
}

impl EpisodeLog {
    pub(crate) fn new(obs_dim: usize, act_dim: usize, horizon: usize) -> Self {
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
    pub(crate) fn record(&mut self, obs: &[f32], action: &[f32], step: &StepResult) -> bool {
        self.observations.extend_from_slice(obs);
        self.actions.extend_from_slice(action);
        self.rewards.push(step.reward);
        self.terminated.push(step.terminated);
        self.truncated.push(step.truncated);
        step.terminated || step.truncated
    }

    /// The episode of `(task, mode)` of the family `env`.
    pub(crate) fn finish(
        self,
        env: &'static str,
        task: usize,
        mode: Mode,
    ) -> Result<Trajectory, CollectError> {
        let Self { obs_dim, act_dim, observations, actions, rewards, terminated, truncated } = self;
        Trajectory::new(obs_dim, act_dim, observations, actions, rewards, terminated, truncated)
            .map_err(|source| CollectError::Data { env, task, mode, source })
    }
}

/// Plays the `episodes` episodes of `(task, mode)`'s `set` one after another, each with its own
/// generator ([`episode_rng`] of `cfg`'s seed), checking [`CollectConfig::interrupt`] before each
/// and counting each in [`CollectConfig::episodes_played`].
/// `play` returns an episode and whether it succeeded. Also returns the fraction that succeeded,
/// for a family with a success rule (`None` without one).
pub(crate) fn play_set(
    cfg: &CollectConfig,
    task: usize,
    mode: Mode,
    set: Set,
    episodes: usize,
    success_rule: bool,
    mut play: impl FnMut(&mut ChaCha8Rng) -> Result<(Trajectory, bool), CollectError>,
) -> Result<(Vec<Trajectory>, Option<f64>), CollectError> {
    let mut trajectories = Vec::with_capacity(episodes);
    let mut wins = 0usize;
    for e in 0..episodes {
        if cfg.interrupt.is_set() {
            return Err(CollectError::Interrupted);
        }
        let (traj, succeeded) = play(&mut episode_rng(cfg.seed, task, mode, set, e))?;
        cfg.episodes_played.add(1);
        wins += usize::from(succeeded);
        trajectories.push(traj);
    }
    Ok((trajectories, success_rule.then(|| wins as f64 / episodes.max(1) as f64)))
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
    let family = cfg.family;
    let env = family.name();
    let (trajectories, success) = family.policies().episodes(cfg, task, mode, set, episodes)?;
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
    if cfg.family.takes_action_noise() {
        info["action_noise_std"] = cfg.reach_action_noise.into();
    }
    info
}
