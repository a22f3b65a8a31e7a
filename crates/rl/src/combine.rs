//! Per-task experts from several snapshots: one agent directory whose expert may differ by task.
//!
//! Why: one task-conditioned agent per family is what fits a 2-core budget, but such an agent can
//! settle on a gait that serves only some tasks (the Ant-Dir agent walks well towards about half of
//! the directions and barely moves towards the others), and its best snapshot overall is not the
//! best for every task (a Cheetah-Vel snapshot can track low speeds better than a later one that
//! tracks high speeds better). The reference trained one agent per task, so its experts are each
//! the best for their task; this recovers that from a run, runs fine-tuned on some tasks
//! (`collect --resume --tasks --sample-recent`), and, for Ant-Dir, the body's symmetries: a
//! snapshot acting through a reflection or the half turn walks towards the mirror images of the
//! directions it walks towards ([`Mirror`]).
//!
//! Selection: every snapshot file records a one-episode deterministic evaluation per task (a
//! mirrored candidate's is read off the task nearest to the mirrored goal). For each task the
//! `top_k` candidates by that record are evaluated again on `eval_episodes` episodes (the same reset
//! states for all of them) and the best mean wins; ties go to the earlier candidate, the base
//! agent's expert first. The medium policy is, of the base agent's medium and the candidates, the
//! one whose recorded returns are on average closest to each task's halfway point between random
//! actions (the base agent's evaluation) and the task's chosen expert.

use crate::agent::{Mirror, Noise, TaskEncoder};
use crate::policy::{self, Policy};
use crate::rollout::Behaviour;
use crate::train::{evaluate_tasks, read_agent_card, AgentCard, TaskExpert};
use crate::{write_atomic, RlError};
use pdt_envs::EnvFamily;
use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tch::Device;

/// What to combine.
#[derive(Debug, Clone, PartialEq)]
pub struct CombineConfig {
    /// A finished agent directory (`agent.json`, `expert.safetensors`, `medium.safetensors`).
    pub base: PathBuf,
    /// Directories of snapshot policy files (a run's `snapshots/`), or single policy files.
    pub candidates: Vec<PathBuf>,
    /// Snapshots re-evaluated per task (the best by their recorded evaluation).
    pub top_k: usize,
    /// Deterministic evaluation episodes per (task, snapshot).
    pub eval_episodes: usize,
    /// Seed of the evaluation episodes.
    pub seed: u64,
    /// Also try every candidate mirrored by the body's symmetries (Ant-Dir; see
    /// [`Mirror`]).
    pub mirrors: bool,
    /// Recorded in the card as `dataset_noise` (how `collect --from-pretrained` writes data);
    /// `None` keeps the base agent's.
    pub dataset_noise: Option<Noise>,
}

impl Default for CombineConfig {
    fn default() -> Self {
        Self {
            base: PathBuf::new(),
            candidates: vec![],
            top_k: 3,
            eval_episodes: 5,
            seed: 0,
            mirrors: true,
            dataset_noise: None,
        }
    }
}

/// Mean deterministic return of `policy` on each of `tasks`, `episodes` per task: the evaluation
/// [`combine`] ranks snapshots by (the episodes depend on the seed and the task only).
pub fn evaluate_policy(
    policy: &Policy,
    family: &dyn EnvFamily,
    tasks: &[usize],
    episodes: usize,
    seed: u64,
    device: Device,
) -> Result<Vec<f64>, RlError> {
    evaluate_through(policy, &policy.meta.encoder, family, tasks, episodes, seed, device)
}

/// [`evaluate_policy`] with another encoder for the same actor (a mirror of its own).
fn evaluate_through(
    policy: &Policy,
    encoder: &TaskEncoder,
    family: &dyn EnvFamily,
    tasks: &[usize],
    episodes: usize,
    seed: u64,
    device: Device,
) -> Result<Vec<f64>, RlError> {
    let behaviour = Behaviour::Actor {
        actor: &policy.actor,
        head: policy.meta.head,
        encoder,
        noise: Noise::Deterministic,
        device,
    };
    evaluate_tasks(family, behaviour, seed, tasks, episodes)
}

struct Candidate {
    path: PathBuf,
    /// The file as read (copied as it is into the combined agent).
    bytes: Vec<u8>,
    policy: Policy,
}

/// A candidate as it is, or mirrored.
struct Variant {
    cand: usize,
    mirror: Option<Mirror>,
}

/// Builds the combined agent in `out` (which may not be the base directory) and returns its card.
/// `progress(done, total)` counts evaluated candidates.
pub fn combine(
    cfg: &CombineConfig,
    out: &Path,
    device: Device,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<AgentCard, RlError> {
    if cfg.top_k == 0 || cfg.eval_episodes == 0 {
        return Err(RlError::Config("top_k and eval_episodes must be at least 1".into()));
    }
    let same = |a: &Path, b: &Path| match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    if same(&cfg.base, out) {
        return Err(RlError::Config(format!(
            "the combined agent must go to a new directory, not the base {}",
            cfg.base.display()
        )));
    }
    let base = read_agent_card(&cfg.base)?;
    let family = pdt_envs::family(&base.family)?;
    let cands = candidates(cfg, &base.family, family.num_tasks(), device)?;

    // Variants: every candidate as it is, and (Ant-Dir) mirrored by each of the body's symmetries.
    let mirrors = if cfg.mirrors { Mirror::for_family(&base.family) } else { vec![] };
    let mut variants: Vec<Variant> = Vec::new();
    for c in 0..cands.len() {
        variants.push(Variant { cand: c, mirror: None });
        for m in &mirrors {
            variants.push(Variant { cand: c, mirror: Some(m.clone()) });
        }
    }
    let pool = Pool { cands: &cands, variants: &variants, family: family.as_ref() };
    let chosen = pool.choose(cfg, device, progress)?;
    let (main, file_of) = pool.write_experts(&chosen, out)?;
    let medium = pool.medium(cfg, &base, &chosen, device)?;
    write_atomic(&out.join("medium.safetensors"), &medium.bytes)?;

    let task_experts: Vec<TaskExpert> = chosen
        .iter()
        .enumerate()
        .map(|(task, &(v, r))| TaskExpert {
            task,
            file: file_of[&v].clone(),
            source: cands[variants[v].cand].path.display().to_string(),
            mirror: variants[v].mirror.as_ref().map(|m| m.name.clone()),
            step: cands[variants[v].cand].policy.meta.step,
            eval_return: r,
        })
        .collect();
    let mut card = base.clone();
    card.expert_step = cands[variants[main].cand].policy.meta.step;
    card.expert_eval = chosen.iter().map(|&(_, r)| r).collect();
    card.task_experts = task_experts;
    card.medium_step = medium.meta.step;
    card.medium_eval = medium.meta.eval_returns.clone();
    card.why_medium = format!(
        "of the base agent's medium and the {} candidate snapshots, the one whose deterministic \
         returns are on average closest ({:.2}) to each task's halfway point between uniform \
         random actions and its expert ({})",
        cands.len(),
        medium.gap,
        medium.path.display()
    );
    if cfg.dataset_noise.is_some() {
        card.dataset_noise = cfg.dataset_noise;
    }
    let text = serde_json::to_string_pretty(&card).map_err(|e| RlError::Config(e.to_string()))?;
    write_atomic(&out.join("agent.json"), format!("{text}\n").as_bytes())?;
    Ok(card)
}

/// The candidates: the base expert first, then every policy file given, in name order (a
/// directory's `*.safetensors`), each once, each checked to be of the family with one recorded
/// return per task.
fn candidates(
    cfg: &CombineConfig,
    family: &str,
    n_tasks: usize,
    device: Device,
) -> Result<Vec<Candidate>, RlError> {
    let mut paths = vec![cfg.base.join("expert.safetensors")];
    for c in &cfg.candidates {
        if c.is_dir() {
            let mut files: Vec<PathBuf> = std::fs::read_dir(c)
                .map_err(|source| RlError::Io { path: c.clone(), source })?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "safetensors"))
                .collect();
            files.sort();
            if files.is_empty() {
                return Err(RlError::File {
                    path: c.clone(),
                    message: "no policy files (*.safetensors) in this directory".into(),
                });
            }
            paths.extend(files);
        } else {
            paths.push(c.clone());
        }
    }
    let mut cands: Vec<Candidate> = Vec::with_capacity(paths.len());
    for path in paths {
        // The same actor twice (the base expert is also one of its run's snapshots) would take
        // two of a task's top_k places: keep the first.
        let bytes = pdt_base::fs::read_limited(&path, pdt_base::fs::MAX_TENSOR_FILE_BYTES)
            .map_err(|source| RlError::Io { path: path.clone(), source })?;
        if cands.iter().any(|c| c.bytes == bytes) {
            continue;
        }
        let policy = policy::from_bytes(&bytes, &path, device)?;
        let bad = |message: String| RlError::File { path: path.clone(), message };
        if policy.meta.family != family {
            return Err(bad(format!(
                "a {} policy, but the base agent is {family}",
                policy.meta.family
            )));
        }
        if policy.meta.eval_returns.len() != n_tasks {
            return Err(bad(format!(
                "records {} evaluation returns, expected one per task ({n_tasks})",
                policy.meta.eval_returns.len()
            )));
        }
        cands.push(Candidate { path, bytes, policy });
    }
    Ok(cands)
}

/// The candidates and their variants, of one family.
struct Pool<'a> {
    cands: &'a [Candidate],
    variants: &'a [Variant],
    family: &'a dyn EnvFamily,
}

/// The medium policy chosen: its file, as read, and how far its returns are from halfway.
struct Medium<'a> {
    path: PathBuf,
    bytes: Cow<'a, [u8]>,
    meta: Cow<'a, policy::PolicyMeta>,
    gap: f64,
}

impl Pool<'_> {
    /// A variant's recorded evaluation on `task`. A mirrored variant's is taken to be the
    /// candidate's on the task whose feature is nearest to the mirrored feature (a proxy used for
    /// ranking only).
    fn recorded(&self, v: &Variant, task: usize) -> f64 {
        let features = &self.cands[0].policy.meta.encoder.task_features;
        let r = &self.cands[v.cand].policy.meta.eval_returns;
        let Some(m) = &v.mirror else { return r[task] };
        let f: Vec<f32> =
            features[task].iter().zip(&m.task_feature_sign).map(|(x, s)| x * s).collect();
        let dist =
            |k: usize| -> f32 { features[k].iter().zip(&f).map(|(a, b)| (a - b) * (a - b)).sum() };
        let n_tasks = self.family.num_tasks();
        let nearest = (0..n_tasks).min_by(|&a, &b| dist(a).total_cmp(&dist(b))).unwrap_or(task);
        r[nearest]
    }

    /// Per task, the variant chosen and its mean return: the `top_k` variants by their recorded
    /// evaluation evaluated again, the best mean winning (ties to the earlier variant).
    fn choose(
        &self,
        cfg: &CombineConfig,
        device: Device,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<Vec<(usize, f64)>, RlError> {
        let (variants, n_tasks) = (self.variants, self.family.num_tasks());
        let mut to_eval: BTreeMap<usize, Vec<usize>> = BTreeMap::new(); // variant -> tasks
        for task in 0..n_tasks {
            let mut order: Vec<usize> = (0..variants.len()).collect();
            order.sort_by(|&a, &b| {
                let (ra, rb) =
                    (self.recorded(&variants[a], task), self.recorded(&variants[b], task));
                rb.total_cmp(&ra).then(a.cmp(&b))
            });
            for &v in order.iter().take(cfg.top_k) {
                to_eval.entry(v).or_default().push(task);
            }
        }
        // (task) -> [(variant, mean return)]
        let mut scores: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n_tasks];
        let total = to_eval.len();
        for (done, (&v, tasks)) in to_eval.iter().enumerate() {
            let p = &self.cands[variants[v].cand].policy;
            let encoder =
                TaskEncoder { mirror: variants[v].mirror.clone(), ..p.meta.encoder.clone() };
            let (episodes, seed) = (cfg.eval_episodes, cfg.seed);
            let returns =
                evaluate_through(p, &encoder, self.family, tasks, episodes, seed, device)?;
            for (&t, r) in tasks.iter().zip(returns) {
                scores[t].push((v, r));
            }
            progress(done + 1, total);
        }
        scores
            .iter()
            .enumerate()
            .map(|(t, s)| {
                s.iter()
                    .copied()
                    .max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)))
                    .ok_or_else(|| RlError::Config(format!("no candidate evaluated for task {t}")))
            })
            .collect()
    }

    /// Writes the chosen experts: the variant chosen for most tasks is `expert.safetensors`, the
    /// others `expert-1.safetensors`, ... in the order of their first task. Returns the main
    /// variant and each chosen variant's file.
    fn write_experts(
        &self,
        chosen: &[(usize, f64)],
        out: &Path,
    ) -> Result<(usize, BTreeMap<usize, String>), RlError> {
        let mut uses: BTreeMap<usize, usize> = BTreeMap::new();
        for &(v, _) in chosen {
            *uses.entry(v).or_default() += 1;
        }
        let by_use = |a: &(&usize, &usize), b: &(&usize, &usize)| a.1.cmp(b.1).then(b.0.cmp(a.0));
        let main = uses.iter().max_by(by_use).map(|(&v, _)| v).unwrap_or(0);
        let mut file_of: BTreeMap<usize, String> =
            BTreeMap::from([(main, "expert.safetensors".into())]);
        for &(v, _) in chosen {
            let k = file_of.len();
            file_of.entry(v).or_insert_with(|| format!("expert-{k}.safetensors"));
        }
        std::fs::create_dir_all(out)
            .map_err(|source| RlError::Io { path: out.to_path_buf(), source })?;
        for (&v, name) in &file_of {
            let c = &self.cands[self.variants[v].cand];
            match &self.variants[v].mirror {
                // As it is: a byte copy of the snapshot.
                None => write_atomic(&out.join(name), &c.bytes)?,
                // Mirrored: the same actor, with the mirror in its encoder.
                Some(m) => {
                    let mut meta = c.policy.meta.clone();
                    meta.encoder.mirror = Some(m.clone());
                    policy::save(&out.join(name), &c.policy.actor, &meta)?;
                }
            }
        }
        Ok((main, file_of))
    }

    /// The medium policy keeps its definition (halfway in evaluated return between uniform random
    /// actions and the expert), now against the per-task experts, task by task: of the base
    /// agent's medium and the candidates as they are, the one whose recorded returns are on
    /// average closest to each task's halfway point (a policy that walks well in half of the
    /// directions and not at all in the others is not medium data).
    fn medium<'b>(
        &'b self,
        cfg: &CombineConfig,
        base: &AgentCard,
        chosen: &[(usize, f64)],
        device: Device,
    ) -> Result<Medium<'b>, RlError> {
        let half: Vec<f64> =
            base.random_eval.iter().zip(chosen).map(|(r, c)| 0.5 * (r + c.1)).collect();
        let gap = |r: &[f64]| -> f64 {
            r.iter().zip(&half).map(|(a, h)| (a - h).abs()).sum::<f64>() / half.len().max(1) as f64
        };
        let path = cfg.base.join("medium.safetensors");
        let bytes = pdt_base::fs::read_limited(&path, pdt_base::fs::MAX_TENSOR_FILE_BYTES)
            .map_err(|source| RlError::Io { path: path.clone(), source })?;
        let meta = policy::from_bytes(&bytes, &path, device)?.meta;
        let mut best: Option<&Candidate> = None;
        let mut best_gap = gap(&meta.eval_returns);
        for c in self.cands {
            let g = gap(&c.policy.meta.eval_returns);
            if g < best_gap {
                (best, best_gap) = (Some(c), g);
            }
        }
        Ok(match best {
            Some(c) => Medium {
                path: c.path.clone(),
                bytes: Cow::Borrowed(&c.bytes),
                meta: Cow::Borrowed(&c.policy.meta),
                gap: best_gap,
            },
            None => {
                Medium { path, bytes: Cow::Owned(bytes), meta: Cow::Owned(meta), gap: best_gap }
            }
        })
    }
}
