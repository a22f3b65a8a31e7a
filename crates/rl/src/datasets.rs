//! Datasets from trained agents: for every task, the main dataset D_i and a prompt set P_i for
//! each of `expert`, `medium` and `random`, in the native format, with a `dataset.json` card.
//!
//! The paper's section 6.3 takes the last / middle / first 500 trajectories of a replay buffer.
//! Here the data comes from **policy snapshots** instead: the expert snapshot, a medium snapshot
//! (halfway in evaluated return between random and expert, see `train::finish`), and uniform
//! random actions (what a replay buffer's first trajectories are, since SAC and TD3 start with
//! uniform random steps). Why: the committed pretrained agents must rebuild every dataset in
//! minutes without retraining, and a replay buffer (hundreds of MB) cannot be committed. Actions
//! carry the policy's own exploration noise by default (a SAC sample, TD3's Gaussian noise), as
//! in a replay buffer.
//!
//! Every episode has its own generator keyed by (seed, task, mode, set, episode): the data is a
//! function of the seed and the settings. It does not depend on the number of threads; the chunk
//! size (how many episodes share one actor forward) is part of the settings, since a batched
//! matmul may round the last bit differently for different batch sizes.

use crate::agent::Noise;
use crate::policy::{self, Policy};
use crate::rollout::{run_episodes, Behaviour, EpisodeSpec};
use crate::train::{read_agent_card, AgentCard};
use crate::RlError;
use pdt_data::mode::{Mode, Set};
use pdt_data::native::{
    self, CardFile, CardTask, DatasetCard, FileMeta, ReturnStats, CARD_FILE_NAME, CARD_FORMAT_NAME,
    FORMAT_VERSION,
};
use pdt_data::TaskDataset;
use pdt_envs::collect_scripted::episode_rng;
use rand::Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use tch::Device;

/// What to generate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetConfig {
    pub seed: u64,
    /// Episodes of each main dataset D_i.
    pub episodes: usize,
    /// Episodes of each prompt set P_i.
    pub prompt_episodes: usize,
    pub modes: Vec<Mode>,
    /// Task indices; empty: all of the family's.
    pub tasks: Vec<usize>,
    /// Exploration noise (as in a replay buffer) or the deterministic policy; `None`: what the
    /// agent's card asks for (`dataset_noise`), else exploration noise.
    pub noise: Option<Noise>,
    /// Episodes stepped together (sets the actor's batch size, which the data depends on).
    pub chunk: usize,
    /// Threads stepping the environments (the data does not depend on this).
    pub threads: usize,
    /// A request to stop now (a front end's Ctrl-C), checked before every step of the episodes:
    /// the call then returns [`RlError::Interrupted`]; the files already written are whole
    /// (each is written atomically) and the card is not written. Not a setting: never serialised.
    #[serde(skip)]
    pub interrupt: pdt_base::stop::StopFlag,
}

impl Default for DatasetConfig {
    fn default() -> Self {
        Self {
            seed: 0,
            episodes: 100,
            prompt_episodes: 5,
            modes: Mode::ALL.to_vec(),
            tasks: vec![],
            noise: None,
            chunk: 256,
            threads: pdt_base::threads::available_cores(),
            interrupt: pdt_base::stop::StopFlag::default(),
        }
    }
}

/// Return statistics of one (task, mode).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskModeStats {
    pub task: usize,
    pub mode: Mode,
    pub dataset: ReturnStats,
    pub prompts: ReturnStats,
}

/// What [`generate`] wrote.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetSummary {
    pub family: String,
    pub entries: Vec<TaskModeStats>,
    pub card: PathBuf,
    pub files: usize,
    pub steps: usize,
}

impl DatasetSummary {
    pub fn get(&self, task: usize, mode: Mode) -> Option<&TaskModeStats> {
        self.entries.iter().find(|e| e.task == task && e.mode == mode)
    }
}

/// Generates the datasets of `cfg` from the agent in `agent_dir` (an `agent.json` plus
/// `expert.safetensors` / `medium.safetensors`) into `out_dir`. `progress(done, total)` counts
/// episodes.
pub fn generate(
    agent_dir: &Path,
    out_dir: &Path,
    cfg: &DatasetConfig,
    device: Device,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<DatasetSummary, RlError> {
    let card = read_agent_card(agent_dir)?;
    let family = pdt_envs::family(&card.family)?;
    let tasks = checked_tasks(cfg, &card.family, family.num_tasks())?;
    std::fs::create_dir_all(out_dir)
        .map_err(|source| RlError::Io { path: out_dir.to_path_buf(), source })?;
    let noise = cfg.noise.or(card.dataset_noise).unwrap_or(Noise::Explore);
    let per_task = cfg.episodes + cfg.prompt_episodes;
    let mut play = Play {
        card: &card,
        agent_dir,
        family: family.as_ref(),
        cfg,
        tasks: &tasks,
        noise,
        device,
        done: 0,
        total: tasks.len() * per_task * cfg.modes.len(),
        progress,
    };
    let mut entries = Vec::new();
    let mut card_files: Vec<Vec<CardFile>> = vec![Vec::new(); tasks.len()];
    let (mut files, mut steps) = (0, 0);
    for &mode in &cfg.modes {
        let by_task = play.mode(mode)?;
        let mut trajs = by_task.into_iter().flatten();
        for (k, &task) in tasks.iter().enumerate() {
            let mut stats = Vec::new();
            for (set, n) in [(Set::Dataset, cfg.episodes), (Set::Prompt, cfg.prompt_episodes)] {
                let ds = TaskDataset::new(trajs.by_ref().take(n).collect())
                    .map_err(|source| RlError::Data { path: out_dir.to_path_buf(), source })?;
                let file_mode = match set {
                    Set::Dataset => mode.name().to_string(),
                    Set::Prompt => format!("prompt-{}", mode.name()),
                };
                let name = format!(
                    "{}.{}",
                    native::task_file_stem(&card.family, task, &file_mode),
                    native::FILE_EXTENSION
                );
                let path = out_dir.join(&name);
                native::write_task_dataset(
                    &path,
                    &ds,
                    &FileMeta::new(card.family.as_str(), task, file_mode.clone()),
                )
                .map_err(|source| RlError::Data { path: path.clone(), source })?;
                files += 1;
                steps += ds.num_steps();
                stats.push(ReturnStats::of(&ds.returns()));
                card_files[k].push(CardFile::describe(name, file_mode, &ds));
            }
            entries.push(TaskModeStats { task, mode, dataset: stats[0], prompts: stats[1] });
        }
    }
    let card_tasks = tasks
        .iter()
        .zip(card_files)
        .map(|(&task, files)| {
            Ok(CardTask { index: task, params: family.task_params(task)?, files })
        })
        .collect::<Result<Vec<_>, RlError>>()?;
    let dataset_card = dataset_card(&card, family.as_ref(), cfg, &tasks, noise, card_tasks);
    native::write_card(out_dir, &dataset_card)
        .map_err(|source| RlError::Data { path: out_dir.join(CARD_FILE_NAME), source })?;
    Ok(DatasetSummary {
        family: card.family,
        entries,
        card: out_dir.join(CARD_FILE_NAME),
        files,
        steps,
    })
}

/// The tasks `cfg` names (all of the family's where it names none), each checked to be one of
/// the family's; and episodes and modes checked not to be empty.
fn checked_tasks(cfg: &DatasetConfig, env: &str, n_tasks: usize) -> Result<Vec<usize>, RlError> {
    let tasks: Vec<usize> =
        if cfg.tasks.is_empty() { (0..n_tasks).collect() } else { cfg.tasks.clone() };
    if let Some(&t) = tasks.iter().find(|&&t| t >= n_tasks) {
        return Err(
            pdt_envs::EnvError::UnknownTask { env: env.to_string(), task: t, n: n_tasks }.into()
        );
    }
    if cfg.episodes == 0 || cfg.prompt_episodes == 0 || cfg.modes.is_empty() {
        return Err(RlError::Config(
            "episodes, prompt_episodes and modes must not be empty".into(),
        ));
    }
    Ok(tasks)
}

/// The policy file `file` of the agent directory, checked to be one of `family`'s.
fn load_policy(
    agent_dir: &Path,
    family: &str,
    file: &str,
    device: Device,
) -> Result<Policy, RlError> {
    // `task_experts` names files inside the agent directory, never elsewhere.
    if file.contains(['/', '\\']) || file.starts_with('.') {
        return Err(RlError::File {
            path: agent_dir.join("agent.json"),
            message: format!("expert file `{file}` is not a file name in the agent directory"),
        });
    }
    let p = policy::load(&agent_dir.join(file), device)?;
    if p.meta.family != family {
        return Err(RlError::File {
            path: agent_dir.join(file),
            message: format!("a {} policy in a {family} agent directory", p.meta.family),
        });
    }
    Ok(p)
}

/// The episodes of every mode, counted as they are played.
struct Play<'a> {
    card: &'a AgentCard,
    agent_dir: &'a Path,
    family: &'a dyn pdt_envs::EnvFamily,
    cfg: &'a DatasetConfig,
    tasks: &'a [usize],
    noise: Noise,
    device: Device,
    /// Episodes played so far, of `total`.
    done: usize,
    total: usize,
    progress: &'a mut dyn FnMut(usize, usize),
}

impl Play<'_> {
    /// The episodes of `mode`, per task of `tasks` (its dataset's, then its prompt set's), each
    /// acted by the mode's policy: uniform random actions, the medium snapshot, or the expert
    /// (which may differ by task: the expert of a combined agent).
    fn mode(&mut self, mode: Mode) -> Result<Vec<Vec<pdt_data::Trajectory>>, RlError> {
        let cfg = self.cfg;
        let per_task = cfg.episodes + cfg.prompt_episodes;
        // Which policy acts on which tasks: one group, except for the expert of a combined agent.
        let mut groups: Vec<(Option<String>, Vec<usize>)> = Vec::new();
        for &task in self.tasks {
            let file = match mode {
                Mode::Expert => Some(self.card.expert_file(task).to_string()),
                Mode::Medium => Some("medium.safetensors".to_string()),
                Mode::Random => None,
            };
            match groups.iter_mut().find(|(f, _)| *f == file) {
                Some((_, ts)) => ts.push(task),
                None => groups.push((file, vec![task])),
            }
        }
        let mut by_task: Vec<Vec<pdt_data::Trajectory>> = vec![Vec::new(); self.tasks.len()];
        for (file, group_tasks) in &groups {
            let load = |f: &str| load_policy(self.agent_dir, &self.card.family, f, self.device);
            let policy = file.as_deref().map(load).transpose()?;
            let behaviour = match &policy {
                Some(p) => Behaviour::Actor {
                    actor: &p.actor,
                    head: p.meta.head,
                    encoder: &p.meta.encoder,
                    noise: self.noise,
                    device: self.device,
                },
                None => Behaviour::Uniform,
            };
            let mut specs = Vec::with_capacity(group_tasks.len() * per_task);
            for &task in group_tasks {
                for (set, n) in [(Set::Dataset, cfg.episodes), (Set::Prompt, cfg.prompt_episodes)] {
                    for e in 0..n {
                        let mut rng = episode_rng(cfg.seed, task, mode, set, e);
                        let reset_seed = rng.random();
                        specs.push(EpisodeSpec { task, reset_seed, rng });
                    }
                }
            }
            let (done, total) = (self.done, self.total);
            let progress = &mut *self.progress;
            let trajs = run_episodes(
                self.family,
                behaviour,
                specs,
                cfg.chunk,
                cfg.threads,
                &mut |d| progress(done + d, total),
                &cfg.interrupt,
            )?;
            self.done += trajs.len();
            let mut trajs = trajs.into_iter();
            for &task in group_tasks {
                if let Some(k) = self.tasks.iter().position(|&t| t == task) {
                    by_task[k] = trajs.by_ref().take(per_task).collect();
                }
            }
        }
        Ok(by_task)
    }
}

/// The card of the datasets written: the family, the tasks' files and how they were made.
fn dataset_card(
    card: &AgentCard,
    family: &dyn pdt_envs::EnvFamily,
    cfg: &DatasetConfig,
    tasks: &[usize],
    noise: Noise,
    card_tasks: Vec<CardTask>,
) -> DatasetCard {
    let preset = family.preset();
    DatasetCard {
        format: CARD_FORMAT_NAME.to_owned(),
        format_version: FORMAT_VERSION.to_owned(),
        env: card.family.clone(),
        obs_dim: preset.obs_dim,
        act_dim: preset.act_dim,
        tasks: card_tasks,
        generator: serde_json::json!({
            "name": "pdt-rl datasets",
            "version": env!("CARGO_PKG_VERSION"),
            "algorithm": card.algorithm,
            "agent_training_seed": card.config.seed,
            "agent_training_steps": card.config.total_steps,
            "seed": cfg.seed,
            "episodes_per_task": cfg.episodes,
            "prompt_episodes": cfg.prompt_episodes,
            "noise": noise,
            "policies": {
                "expert": if card.task_experts.is_empty() {
                    format!("the {} actor snapshot at step {} (best evaluated)", card.algorithm.name(), card.expert_step)
                } else {
                    format!("per task, the best evaluated of several {} actor snapshots (see expert_per_task)", card.algorithm.name())
                },
                "medium": format!("the {} actor snapshot at step {} ({})", card.algorithm.name(), card.medium_step, card.why_medium),
                "random": "uniform random actions in [-1, 1] (the first episodes of a replay buffer)",
            },
            "expert_per_task": card.task_experts.iter().filter(|e| tasks.contains(&e.task)).map(|e| serde_json::json!({
                "task": e.task, "file": e.file, "source": e.source, "step": e.step, "eval_return": e.eval_return,
            })).collect::<Vec<_>>(),
            "rng": "ChaCha8, one generator per episode keyed by (seed, task, mode, set, episode): reset seed, then action noise",
        }),
    }
}
