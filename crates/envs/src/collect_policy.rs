//! Collection in a task suite's own environment from a user's Python policy: the expert, medium
//! and random datasets of each task, their prompt sets and a `dataset.json` card, as the scripted
//! families' collection writes them (`collect_scripted`), for a user who has a policy but no data.
//!
//! The environments and the policy live on the Python side of the worker protocol
//! ([`crate::worker::Acting`]): a worker process of the suite's `[environment]` (`promptdt
//! collect --policy module:callable`), or the calling interpreter (Python's `promptdt.collect(
//! policy=...)`, through another [`Transport`]); the levels, the noise, the seeds, the checks and
//! the files are this module's, so both give the same bytes. One request per vector step of all
//! running episodes: the step's reply carries the policy's action on each new observation.
//!
//! Levels (`docs/your-own-tasks.md`): `expert` is the policy (with `action_noise`, default none),
//! `medium` a second policy when given, else the expert with Gaussian noise `medium_noise`, and
//! `random` uniform actions in the suite's bounds. Noise is a standard deviation in units of each
//! action dimension's half-range, and every action is clipped into the bounds (the dataset
//! records the action the environment was given). Prompt sets are made from each task's data by
//! a [`PromptRule`] (`best:N`, as `promptdt data import` makes them).
//!
//! Every random choice comes from the one seed: each episode has its own generator
//! ([`episode_rng`] of `(seed, task, mode, episode)`), which draws its reset seed first and then
//! its actions' noise, so the data does not depend on how many environments run at once or in
//! which order episodes end (given a policy and an environment that are functions of the seeded
//! reset and the observation).

use std::collections::{BTreeMap, VecDeque};
use std::path::Path;

use pdt_data::flat::PromptRule;
use pdt_data::mode::{Mode, Set};
use pdt_data::native::{
    self, CardFile, CardTask, DatasetCard, FileMeta, CARD_FILE_NAME, CARD_FORMAT_NAME,
    FORMAT_VERSION,
};
use pdt_data::{TaskDataset, Trajectory};
use rand::{Rng, RngCore};
use rand_chacha::ChaCha8Rng;

use crate::collect_scripted::{episode_rng, CollectError, CollectSummary, TaskModeSummary};
use crate::suite::SuiteFamily;
use crate::vec_env::EnvDims;
use crate::worker::{Acting, Transport};
use crate::{ActionBounds, EnvError, EnvFamily, StepResult};

/// Default standard deviation (in half-ranges) of the medium level's noise on the expert.
pub const DEFAULT_MEDIUM_NOISE: f64 = 0.5;
/// Default environments per task stepped together.
pub const DEFAULT_ENVS_PER_TASK: usize = 10;

/// What to collect ([`PolicyCollectConfig::new`] gives the defaults).
#[derive(Debug, Clone)]
pub struct PolicyCollectConfig {
    pub seed: u64,
    /// Episodes in each dataset D_i.
    pub episodes_per_task: usize,
    /// How each prompt set is made from its dataset.
    pub prompt_rule: PromptRule,
    pub modes: Vec<Mode>,
    /// Task indices of the suite.
    pub tasks: Vec<usize>,
    /// The expert policy: its `module:callable` (what the card records, and what a worker
    /// process imports).
    pub expert: String,
    /// A second policy for the medium level; `None`: the expert with `medium_noise`.
    pub medium: Option<String>,
    /// Gaussian noise on the expert's (and a medium policy's) actions, in half-ranges.
    pub action_noise: f64,
    /// Gaussian noise on the expert's actions that makes the medium level without a policy of
    /// its own, in half-ranges.
    pub medium_noise: f64,
    /// Environments per task stepped together (the data does not depend on it).
    pub envs_per_task: usize,
    /// A request to stop (a front end's Ctrl-C), checked before every vector step.
    pub interrupt: pdt_base::stop::StopFlag,
    /// Episodes played so far (a front end's progress).
    pub episodes_played: crate::rollout::EpisodeCount,
}

impl PolicyCollectConfig {
    /// Every task of `suite`, every level, 100 episodes, prompts `best:5`, seed 0.
    pub fn new(suite: &SuiteFamily, expert: impl Into<String>) -> Self {
        Self {
            seed: 0,
            episodes_per_task: 100,
            prompt_rule: PromptRule::BestReturn { episodes: 5 },
            modes: Mode::ALL.to_vec(),
            tasks: (0..suite.num_tasks()).collect(),
            expert: expert.into(),
            medium: None,
            action_noise: 0.0,
            medium_noise: DEFAULT_MEDIUM_NOISE,
            envs_per_task: DEFAULT_ENVS_PER_TASK,
            interrupt: Default::default(),
            episodes_played: Default::default(),
        }
    }

    /// Checks the settings against `suite` before anything runs.
    pub fn validate(&self, suite: &SuiteFamily) -> Result<(), CollectError> {
        let bad = |m: String| Err(CollectError::Config(m));
        if self.episodes_per_task == 0 {
            return bad("episodes must be at least 1".into());
        }
        if self.envs_per_task == 0 {
            return bad("envs_per_task must be at least 1".into());
        }
        for (name, v) in [("action_noise", self.action_noise), ("medium_noise", self.medium_noise)]
        {
            if !(v.is_finite() && (0.0..=10.0).contains(&v)) {
                return bad(format!("{name} must be a standard deviation from 0 to 10, got {v}"));
            }
        }
        if self.modes.is_empty() || self.tasks.is_empty() {
            return bad("no modes or no tasks given".into());
        }
        for (what, policy) in
            [("policy", Some(&self.expert)), ("medium policy", self.medium.as_ref())]
        {
            if policy.is_some_and(|p| p.trim().is_empty()) {
                return bad(format!("the {what} has an empty name"));
            }
        }
        let n = suite.num_tasks();
        if let Some(&t) = self.tasks.iter().find(|&&t| t >= n) {
            return Err(EnvError::UnknownTask { env: suite.name().into(), task: t, n }.into());
        }
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

    /// The policy acting at `mode`'s level, by its name in the worker protocol (`None`: random).
    fn policy_of(&self, mode: Mode) -> Option<&'static str> {
        match mode {
            Mode::Expert => Some("expert"),
            Mode::Medium if self.medium.is_some() => Some("medium"),
            Mode::Medium => Some("expert"),
            Mode::Random => None,
        }
    }

    /// The noise on `mode`'s policy action, in half-ranges.
    fn noise_of(&self, mode: Mode) -> f64 {
        match mode {
            Mode::Medium if self.medium.is_none() => self.medium_noise,
            _ => self.action_noise,
        }
    }
}

/// Where the environments and the policies live.
pub enum PolicySide {
    /// A worker process of the suite's `[environment]`, which imports the policies by their
    /// `module:callable` (`promptdt collect --policy`).
    Worker,
    /// The Python side of `transport`, which was given the policies' callables; it makes the
    /// environments by the suite's `[environment]` where `suite_environment`, else by a factory
    /// of its own (Python's `promptdt.collect(policy=..., factory=...)`).
    Given { transport: Box<dyn Transport>, suite_environment: bool },
}

/// One episode under way in an environment.
struct Running {
    /// Place of its task in the config's tasks, of its mode in the config's modes.
    task_pos: usize,
    mode_pos: usize,
    episode: usize,
    rng: ChaCha8Rng,
    /// The observation before the next action.
    obs: Vec<f32>,
    /// The policy's action for `obs` (none at the random level).
    proposal: Option<Vec<f32>>,
    observations: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    terminated: Vec<bool>,
    truncated: Vec<bool>,
    won: bool,
}

/// Plays the episodes of `cfg` in `suite`'s environment and writes, into `out_dir` (created if
/// missing), each task's `{name}-{i}-{mode}.safetensors` and `{name}-{i}-prompt-{mode}.safetensors`
/// as soon as its mode's episodes are all played (each file checked and written atomically), then
/// `dataset.json`. A failure (the policy or the environment raised, a wrong shape, a non-finite
/// value, the worker died or hung) is an error naming the task and step; the files written
/// before it are whole and the card is not written. `progress(done, total)` counts episodes.
pub fn collect(
    suite: &SuiteFamily,
    cfg: &PolicyCollectConfig,
    side: PolicySide,
    out_dir: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<CollectSummary, CollectError> {
    cfg.validate(suite)?;
    let p = suite.preset();
    let dims = EnvDims { obs_dim: p.obs_dim, act_dim: p.act_dim, horizon: p.horizon };
    let lanes = cfg.envs_per_task.min(cfg.episodes_per_task);
    // Environment `k` is lane `k % lanes` of task `cfg.tasks[k / lanes]`.
    let slot_tasks = cfg
        .tasks
        .iter()
        .flat_map(|&t| std::iter::repeat_n(t, lanes))
        .map(|t| suite.worker_task(t))
        .collect::<Result<Vec<_>, _>>()?;
    let mut policies = BTreeMap::new();
    let given = matches!(side, PolicySide::Given { .. });
    policies.insert("expert".to_owned(), (!given).then(|| cfg.expert.clone()));
    if let Some(m) = &cfg.medium {
        policies.insert("medium".to_owned(), (!given).then(|| m.clone()));
    }
    let suite_environment = !matches!(side, PolicySide::Given { suite_environment: false, .. });
    let mut acting = match side {
        PolicySide::Worker => {
            let spec = suite.environment().ok_or_else(|| {
                CollectError::Config(format!(
                    "{} declares no [environment] to collect in (docs/your-own-tasks.md)",
                    suite.path().display()
                ))
            })?;
            let dir = suite.path().parent().unwrap_or(Path::new("."));
            Acting::spawn(spec, dir, slot_tasks, dims, &policies)?
        }
        PolicySide::Given { transport, suite_environment } => {
            let spec = if suite_environment {
                Some(suite.environment().ok_or_else(|| {
                    CollectError::Config(format!(
                        "{} declares no [environment], and no factory was given",
                        suite.path().display()
                    ))
                })?)
            } else {
                None
            };
            Acting::over(transport, spec, slot_tasks, dims, &policies)?
        }
    };
    std::fs::create_dir_all(out_dir)
        .map_err(|source| CollectError::CreateDir { path: out_dir.to_path_buf(), source })?;
    let mut run = Collection::new(suite, cfg, lanes, out_dir);
    run.environment = match (given, suite_environment) {
        (true, false) => Some("a factory given from Python".to_owned()),
        _ => suite.environment().map(|e| e.entry.clone()),
    };
    run.play(&mut acting, progress)?;
    run.finish()
}

/// The episodes of one (task, mode): the finished ones by number, how many remain, how many
/// solved the task.
#[derive(Default)]
struct Pending {
    episodes: Vec<Option<Trajectory>>,
    left: usize,
    wins: usize,
}

/// The state of one collection: each environment's queue of episodes and the finished ones.
struct Collection<'a> {
    suite: &'a SuiteFamily,
    cfg: &'a PolicyCollectConfig,
    out_dir: &'a Path,
    bounds: ActionBounds,
    lanes: usize,
    /// Per environment, the episodes it is still to play: `(mode_pos, episode)`.
    queues: Vec<VecDeque<(usize, usize)>>,
    /// Per (task, mode), its episodes.
    done: Vec<Vec<Pending>>,
    /// The summaries of the (task, mode) pairs written, and their card files.
    written: BTreeMap<(usize, usize), (TaskModeSummary, [CardFile; 2])>,
    /// Whether any step said whether its task was solved.
    success_seen: bool,
    /// What made the environments, for the card.
    environment: Option<String>,
}

impl<'a> Collection<'a> {
    fn new(
        suite: &'a SuiteFamily,
        cfg: &'a PolicyCollectConfig,
        lanes: usize,
        out_dir: &'a Path,
    ) -> Self {
        let n = cfg.tasks.len() * lanes;
        let queues = (0..n)
            .map(|k| {
                let lane = k % lanes;
                (0..cfg.modes.len())
                    .flat_map(|m| (lane..cfg.episodes_per_task).step_by(lanes).map(move |e| (m, e)))
                    .collect()
            })
            .collect();
        let e = cfg.episodes_per_task;
        let done = cfg
            .tasks
            .iter()
            .map(|_| {
                let pending =
                    || Pending { episodes: (0..e).map(|_| None).collect(), left: e, wins: 0 };
                cfg.modes.iter().map(|_| pending()).collect()
            })
            .collect();
        Self {
            suite,
            cfg,
            out_dir,
            bounds: suite.action_bounds(),
            lanes,
            queues,
            done,
            written: BTreeMap::new(),
            success_seen: false,
            environment: None,
        }
    }

    /// Plays every queued episode, one request per vector step (and one per batch of resets).
    fn play(
        &mut self,
        acting: &mut Acting,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<(), CollectError> {
        let n = self.queues.len();
        let ad = self.suite.preset().act_dim;
        let total = self.cfg.tasks.len() * self.cfg.modes.len() * self.cfg.episodes_per_task;
        let mut played = 0;
        let mut running: Vec<Option<Running>> = (0..n).map(|_| None).collect();
        let mut idle: Vec<usize> = (0..n).collect();
        loop {
            if self.cfg.interrupt.is_set() {
                return Err(CollectError::Interrupted);
            }
            self.start(acting, &idle, &mut running)?;
            let mask: Vec<bool> = running.iter().map(Option::is_some).collect();
            if !mask.contains(&true) {
                return Ok(());
            }
            let mut actions = vec![0f32; n * ad];
            let mut sent: Vec<Option<Vec<f32>>> = vec![None; n];
            let mut act: Vec<Option<String>> = vec![None; n];
            for (k, r) in running.iter_mut().enumerate() {
                let Some(r) = r else { continue };
                let mode = self.cfg.modes[r.mode_pos];
                let a = level_action(&self.bounds, self.cfg.noise_of(mode), r);
                actions[k * ad..(k + 1) * ad].copy_from_slice(&a);
                sent[k] = Some(a);
                act[k] = self.cfg.policy_of(mode).map(str::to_owned);
            }
            let (steps, acted) = acting.step(&actions, &mask, &act)?;
            idle.clear();
            for (k, (step, proposal)) in steps.into_iter().zip(acted).enumerate() {
                let (Some(step), Some(a)) = (step, sent[k].take()) else { continue };
                let step = step?;
                let ended = step.terminated || step.truncated;
                let r = running[k].as_mut().ok_or(CollectError::Stopped)?;
                self.record(r, &a, &step)?;
                if ended {
                    let r = running[k].take().ok_or(CollectError::Stopped)?;
                    self.finish_episode(r)?;
                    played += 1;
                    self.cfg.episodes_played.add(1);
                    progress(played, total);
                    idle.push(k);
                } else {
                    r.obs = step.obs;
                    r.proposal = proposal.transpose()?;
                }
            }
        }
    }

    /// Starts the next queued episode of each environment of `idle` (one reset request).
    fn start(
        &mut self,
        acting: &mut Acting,
        idle: &[usize],
        running: &mut [Option<Running>],
    ) -> Result<(), CollectError> {
        let n = running.len();
        let mut seeds: Vec<Option<u64>> = vec![None; n];
        let mut act: Vec<Option<String>> = vec![None; n];
        let mut fresh: Vec<(usize, Running)> = Vec::new();
        for &k in idle {
            let Some((mode_pos, episode)) = self.queues[k].pop_front() else { continue };
            let task_pos = k / self.lanes;
            let mode = self.cfg.modes[mode_pos];
            let task = self.cfg.tasks[task_pos];
            let mut rng = episode_rng(self.cfg.seed, task, mode, Set::Dataset, episode);
            // First draw: the reset seed (below 2^32, which every seeding API takes).
            seeds[k] = Some(u64::from(rng.next_u32()));
            act[k] = self.cfg.policy_of(mode).map(str::to_owned);
            fresh.push((k, self.running(task_pos, mode_pos, episode, rng)));
        }
        if fresh.is_empty() {
            return Ok(());
        }
        let (obs, acted) = acting.reset(&seeds, &act)?;
        let mut acted = acted;
        for (k, mut r) in fresh {
            r.obs = obs[k].clone().ok_or(CollectError::Stopped)?;
            r.proposal = acted[k].take().transpose()?;
            running[k] = Some(r);
        }
        Ok(())
    }

    fn running(
        &self,
        task_pos: usize,
        mode_pos: usize,
        episode: usize,
        rng: ChaCha8Rng,
    ) -> Running {
        let h = self.suite.preset().horizon.min(1024);
        let p = self.suite.preset();
        Running {
            task_pos,
            mode_pos,
            episode,
            rng,
            obs: Vec::new(),
            proposal: None,
            observations: Vec::with_capacity(h * p.obs_dim),
            actions: Vec::with_capacity(h * p.act_dim),
            rewards: Vec::with_capacity(h),
            terminated: Vec::with_capacity(h),
            truncated: Vec::with_capacity(h),
            won: false,
        }
    }

    /// Records one step of `r`'s episode (`action` taken at `r.obs`), its reward checked finite.
    fn record(
        &mut self,
        r: &mut Running,
        action: &[f32],
        step: &StepResult,
    ) -> Result<(), CollectError> {
        let t = r.rewards.len() + 1;
        if !step.reward.is_finite() {
            let task = self.cfg.tasks[r.task_pos];
            return Err(EnvError::Worker {
                task: task_label(self.suite, task),
                step: Some(t),
                message: format!("the environment returned a non-finite reward ({})", step.reward),
            }
            .into());
        }
        r.observations.extend_from_slice(&r.obs);
        r.actions.extend_from_slice(action);
        r.rewards.push(step.reward);
        r.terminated.push(step.terminated);
        r.truncated.push(step.truncated);
        self.success_seen |= step.success.is_some();
        let by_reward = self.suite.success_reward().is_some_and(|s| step.reward >= s);
        r.won |= step.success == Some(true) || by_reward;
        Ok(())
    }

    /// Files a finished episode; writes its (task, mode) once all its episodes are in.
    fn finish_episode(&mut self, r: Running) -> Result<(), CollectError> {
        let p = self.suite.preset();
        let task = self.cfg.tasks[r.task_pos];
        let traj = Trajectory::new(
            p.obs_dim,
            p.act_dim,
            r.observations,
            r.actions,
            r.rewards,
            r.terminated,
            r.truncated,
        )
        .map_err(|e| EnvError::Worker {
            task: task_label(self.suite, task),
            step: None,
            message: format!("episode {} is not a valid trajectory: {e}", r.episode),
        })?;
        let pending = &mut self.done[r.task_pos][r.mode_pos];
        pending.episodes[r.episode] = Some(traj);
        pending.left -= 1;
        pending.wins += usize::from(r.won);
        if pending.left == 0 {
            self.write(r.task_pos, r.mode_pos)?;
        }
        Ok(())
    }

    /// Writes the dataset and prompt set of `(task, mode)`, each checked and atomic.
    fn write(&mut self, task_pos: usize, mode_pos: usize) -> Result<(), CollectError> {
        let (task, mode) = (self.cfg.tasks[task_pos], self.cfg.modes[mode_pos]);
        let Pending { episodes, wins, .. } = std::mem::take(&mut self.done[task_pos][mode_pos]);
        let trajectories: Vec<Trajectory> = episodes.into_iter().flatten().collect();
        let p = self.suite.preset();
        let data = TaskDataset { obs_dim: p.obs_dim, act_dim: p.act_dim, trajectories };
        let prompts = self.cfg.prompt_rule.prompts(&data);
        let name = self.suite.name();
        let mut files = Vec::with_capacity(2);
        let mut paths = Vec::with_capacity(2);
        for (file_mode, ds) in
            [(mode.name().to_owned(), &data), (format!("prompt-{mode}"), &prompts)]
        {
            let file = format!(
                "{}.{}",
                native::task_file_stem(name, task, &file_mode),
                native::FILE_EXTENSION
            );
            let path = self.out_dir.join(&file);
            native::write_task_dataset(&path, ds, &FileMeta::new(name, task, file_mode.clone()))
                .map_err(|source| CollectError::Write { path: path.clone(), source })?;
            files.push(CardFile::describe(file, file_mode, ds));
            paths.push(path);
        }
        let [dataset_file, prompt_file]: [std::path::PathBuf; 2] =
            paths.try_into().map_err(|_| CollectError::Stopped)?;
        let summary = TaskModeSummary {
            task,
            mode,
            dataset: files[0].returns,
            prompts: files[1].returns,
            dataset_file,
            prompt_file,
            success_rate: Some(wins as f64 / self.cfg.episodes_per_task as f64),
        };
        let files: [CardFile; 2] = files.try_into().map_err(|_| CollectError::Stopped)?;
        self.written.insert((task_pos, mode_pos), (summary, files));
        Ok(())
    }

    /// The card, written last, and the summary.
    fn finish(self) -> Result<CollectSummary, CollectError> {
        let rule = self.success_seen || self.suite.success_reward().is_some();
        let mut entries = Vec::new();
        let mut card_tasks = Vec::new();
        let mut written = self.written;
        for (task_pos, &task) in self.cfg.tasks.iter().enumerate() {
            let mut files = Vec::new();
            for mode_pos in 0..self.cfg.modes.len() {
                let (mut summary, pair) =
                    written.remove(&(task_pos, mode_pos)).ok_or(CollectError::Stopped)?;
                summary.success_rate = summary.success_rate.filter(|_| rule);
                entries.push(summary);
                files.extend(pair);
            }
            card_tasks.push(CardTask { index: task, params: self.suite.task_params(task)?, files });
        }
        let p = self.suite.preset();
        let card = DatasetCard {
            format: CARD_FORMAT_NAME.to_owned(),
            format_version: FORMAT_VERSION.to_owned(),
            env: self.suite.name().to_owned(),
            obs_dim: p.obs_dim,
            act_dim: p.act_dim,
            tasks: card_tasks,
            generator: generator_info(self.cfg, self.environment.as_deref()),
        };
        native::write_card(self.out_dir, &card).map_err(|source| CollectError::Write {
            path: self.out_dir.join(CARD_FILE_NAME),
            source,
        })?;
        Ok(CollectSummary { entries, card: self.out_dir.join(CARD_FILE_NAME) })
    }
}

/// `name (task i)`, as the worker's errors name a task.
fn task_label(suite: &SuiteFamily, task: usize) -> String {
    let name = suite.tasks().get(task).map_or("?", |t| t.name.as_str());
    format!("{name} (task {task})")
}

/// The action of `r`'s level at its current observation: the policy's (`r.proposal`) with
/// Gaussian noise of `noise` half-ranges, or (no proposal: the random level) uniform in the
/// bounds; clipped into the bounds either way. Draws from the episode's generator.
fn level_action(bounds: &ActionBounds, noise: f64, r: &mut Running) -> Vec<f32> {
    let dims = bounds.low.iter().zip(&bounds.high);
    match &r.proposal {
        None => dims
            .map(|(&lo, &hi)| {
                let u: f64 = r.rng.random();
                (f64::from(lo) + (f64::from(hi) - f64::from(lo)) * u) as f32
            })
            .collect(),
        Some(a) => a
            .iter()
            .zip(dims)
            .map(|(&a, (&lo, &hi))| {
                let v = if noise > 0.0 {
                    let half = 0.5 * (f64::from(hi) - f64::from(lo));
                    let n = pdt_base::standard_normal(|| r.rng.random::<f64>());
                    (f64::from(a) + noise * half * n) as f32
                } else {
                    a
                };
                v.clamp(lo, hi)
            })
            .collect(),
    }
}

/// The card's `generator` entry: enough to collect the data again.
fn generator_info(cfg: &PolicyCollectConfig, environment: Option<&str>) -> serde_json::Value {
    let medium = match &cfg.medium {
        Some(m) => {
            format!("the policy {m}, Gaussian action noise {} half-ranges", cfg.action_noise)
        }
        None => format!("the expert with Gaussian action noise {} half-ranges", cfg.medium_noise),
    };
    let policies: serde_json::Map<String, serde_json::Value> = cfg
        .modes
        .iter()
        .map(|m| {
            let text = match m {
                Mode::Expert => format!(
                    "the policy {}, Gaussian action noise {} half-ranges",
                    cfg.expert, cfg.action_noise
                ),
                Mode::Medium => medium.clone(),
                Mode::Random => "uniform actions in the suite's bounds".to_owned(),
            };
            (m.name().to_owned(), text.into())
        })
        .collect();
    serde_json::json!({
        "name": "pdt-envs collect_policy",
        "version": env!("CARGO_PKG_VERSION"),
        "seed": cfg.seed,
        "episodes_per_task": cfg.episodes_per_task,
        "prompt_rule": prompt_rule_name(cfg.prompt_rule),
        "policies": policies,
        "expert_policy": cfg.expert,
        "medium_policy": cfg.medium,
        "action_noise": cfg.action_noise,
        "medium_noise": cfg.medium.is_none().then_some(cfg.medium_noise),
        "environment": environment,
        "actions": "clipped into the suite's bounds; noise in units of each dimension's half-range",
        "rng": "ChaCha8, one generator per episode keyed by (seed, task, mode, episode): the \
                reset seed (below 2^32) first, then the actions' noise; normal noise by Box-Muller",
    })
}

/// `best:N`, as the rule is written on the command line.
fn prompt_rule_name(rule: PromptRule) -> String {
    let PromptRule::BestReturn { episodes } = rule;
    format!("best:{episodes}")
}
