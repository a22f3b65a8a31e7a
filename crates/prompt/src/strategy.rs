//! Test-time prompt strategies (`docs/prompt-control.md`): which demonstration segments
//! form the prompt an evaluated (or served) episode is conditioned on, and how long it is.
//!
//! The one owner of the concept: every front end (`promptdt eval --prompt-strategy`, a run's
//! `[eval.prompt]`, `promptdt serve`'s `prompt_strategy`, the Python `prompt_strategy=`) parses a
//! name into [`PromptStrategyKind`] and a [`PromptStrategy`], and the evaluator and the policy
//! runtime choose segments through [`BatchSampler`]'s methods here.
//!
//! - `reference`: the reference code's rule (`BatchSampler::eval_prompt`), unchanged.
//! - `random-segment`: per prompt slot, a uniformly drawn demonstration and a uniformly drawn
//!   window lying wholly inside it (the paper's Algorithm 2).
//! - `best-return`: the demonstration with the highest return, at the reference's tail position.
//! - `nearest-start`: per episode, the segment whose first state is nearest the episode's start
//!   state, in the run's normalised state space.
//! - `bandit`: [`crate::bandit::SegmentBandit`], over the candidate segments, updated from
//!   episode returns (Rietz et al. 2025).

use crate::batch::{BatchSampler, SegmentBatch};
use crate::config::{SamplerConfig, SamplerError};
use crate::segment::SegmentOut;
use crate::Rng;
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// A named prompt strategy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PromptStrategyKind {
    /// The reference code's rule: a uniformly drawn demonstration, its tail segment.
    #[default]
    Reference,
    /// A uniformly drawn demonstration and a uniformly drawn window inside it, per slot.
    RandomSegment,
    /// The highest-return demonstration (J > 1: the J best), at the tail position.
    BestReturn,
    /// Per episode: the segments whose first states are nearest the episode's start state.
    NearestStart,
    /// A bandit over the candidate segments, updated from episode returns.
    Bandit,
}

impl PromptStrategyKind {
    pub const ALL: [PromptStrategyKind; 5] =
        [Self::Reference, Self::RandomSegment, Self::BestReturn, Self::NearestStart, Self::Bandit];

    /// The name front ends accept (`random-segment`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Reference => "reference",
            Self::RandomSegment => "random-segment",
            Self::BestReturn => "best-return",
            Self::NearestStart => "nearest-start",
            Self::Bandit => "bandit",
        }
    }

    /// Whether the prompt depends on the episode's first observation (chosen at reset).
    pub fn per_episode(self) -> bool {
        self == Self::NearestStart
    }

    /// Whether the strategy learns from episode returns across episodes (evaluated in rounds).
    pub fn learns_from_returns(self) -> bool {
        self == Self::Bandit
    }
}

impl fmt::Display for PromptStrategyKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for PromptStrategyKind {
    type Err = StrategyError;

    fn from_str(s: &str) -> Result<Self, StrategyError> {
        Self::ALL.into_iter().find(|k| k.name() == s).ok_or_else(|| StrategyError::UnknownName {
            name: s.to_string(),
            known: Self::ALL.map(Self::name).join(", "),
        })
    }
}

/// How the bandit picks an arm per slot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BanditRule {
    /// With probability epsilon every slot explores (a uniform arm), else each slot takes its
    /// best mean return so far: the bandit paper's selection (`select_segments`).
    #[default]
    EpsilonGreedy,
    /// UCB1: untried arms first (in a random order drawn from the bandit's seeded generator),
    /// then mean + c * range * sqrt(2 ln n / n_arm).
    Ucb,
}

/// The bandit's settings (`[eval.prompt.bandit]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BanditConfig {
    pub rule: BanditRule,
    /// Exploration probability of `epsilon-greedy` at the first round.
    pub epsilon: f64,
    /// Subtracted from epsilon after every round (the cited code's `epsilon_decay`), floored at
    /// 0. Ignored when `explore_fraction` is set.
    pub epsilon_decay: f64,
    /// Epsilon decays linearly from `epsilon` to 0 over this fraction of the task's rounds (the
    /// cited code: epsilon 1.0, `epsilon_decay = 1 / (0.2 x num_rollouts)`, so 0.2). The decay per
    /// round is then `epsilon / (fraction x rounds)`, which needs the number of rounds: only an
    /// evaluation knows it (`promptdt eval`, a run's evaluations); `None`: `epsilon_decay`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub explore_fraction: Option<f64>,
    /// `ucb`: the exploration coefficient, in units of the range of returns seen so far.
    pub ucb_c: f64,
    /// Episodes per task in one round (they share the round's prompt, run batched together, and
    /// update the bandit after the round). 1 = the paper's one update per episode.
    pub episodes_per_round: usize,
}

impl Default for BanditConfig {
    fn default() -> Self {
        Self {
            rule: BanditRule::EpsilonGreedy,
            epsilon: 0.1,
            epsilon_decay: 0.0,
            explore_fraction: None,
            ucb_c: 1.0,
            episodes_per_round: 1,
        }
    }
}

/// A prompt strategy with its settings: a run's `[eval.prompt]`, a CLI flag, a serve request or
/// a Python keyword. The default is `reference` with the training prompt length, which is what
/// every evaluation did before strategies existed.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PromptStrategy {
    pub strategy: PromptStrategyKind,
    /// Test-time prompt segments J (`None`: the run's `sampler.prompt_episodes`).
    pub episodes: Option<usize>,
    /// Test-time steps per segment H (`None`: the run's prompt length).
    pub length: Option<usize>,
    /// Candidate segments (`nearest-start`, `bandit`) start every `stride` steps of a
    /// demonstration. `None`: 1 for `nearest-start` (every window), H for `bandit` (disjoint
    /// windows, fewer arms for the few episodes an evaluation has).
    pub stride: Option<usize>,
    pub bandit: BanditConfig,
}

impl PromptStrategy {
    /// A strategy by name, other settings at their defaults.
    pub fn named(name: &str) -> Result<Self, StrategyError> {
        Ok(Self { strategy: name.parse()?, ..Self::default() })
    }

    /// Whether this is exactly what evaluations did before strategies (written nowhere then).
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }

    /// The sampler settings of a test-time prompt: the trained ones with J and H replaced where
    /// given. [`BatchSampler::new`] checks that the prompt fits the model (naming the values).
    pub fn sampler_config(&self, trained: &SamplerConfig) -> SamplerConfig {
        SamplerConfig {
            prompt_episodes: self.episodes.unwrap_or(trained.prompt_episodes),
            prompt_length: self.length.unwrap_or(trained.prompt_length),
            ..trained.clone()
        }
    }

    /// The candidate stride for a segment length `h`.
    pub fn stride_for(&self, h: usize) -> usize {
        self.stride.unwrap_or(match self.strategy {
            PromptStrategyKind::Bandit => h,
            _ => 1,
        })
    }

    /// Checks the settings; errors name the field and the value.
    pub fn validate(&self) -> Result<(), StrategyError> {
        let bad = |field: &'static str, why: String| Err(StrategyError::Setting { field, why });
        for (field, v) in
            [("episodes", self.episodes), ("length", self.length), ("stride", self.stride)]
        {
            if v == Some(0) {
                return bad(field, "= 0: must be at least 1".into());
            }
        }
        let b = &self.bandit;
        if !(0.0..=1.0).contains(&b.epsilon) {
            return bad("bandit.epsilon", format!("= {}: must be in [0, 1]", b.epsilon));
        }
        if !(b.epsilon_decay.is_finite() && b.epsilon_decay >= 0.0) {
            return bad("bandit.epsilon_decay", format!("= {}: must be >= 0", b.epsilon_decay));
        }
        if let Some(f) = b.explore_fraction {
            if !(f > 0.0 && f <= 1.0) {
                return bad("bandit.explore_fraction", format!("= {f}: must be in (0, 1]"));
            }
        }
        if !(b.ucb_c.is_finite() && b.ucb_c >= 0.0) {
            return bad("bandit.ucb_c", format!("= {}: must be >= 0", b.ucb_c));
        }
        if b.episodes_per_round == 0 {
            return bad("bandit.episodes_per_round", "= 0: must be at least 1".into());
        }
        Ok(())
    }
}

/// One segment of a prompt: which demonstration of the task's prompt set, from which step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct SegmentChoice {
    /// Index into the task's demonstrations (its prompt set P_i).
    pub demo: usize,
    /// First step of the segment in that demonstration.
    pub start: usize,
}

/// What a strategy chose for one episode (or for a task's episodes), for the evaluation's log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PromptPick {
    /// `cheetah_vel-2`
    pub task: String,
    /// Episode index within its task (the first of the round's, for a bandit round).
    pub episode: usize,
    /// The J segments, in prompt order.
    pub segments: Vec<SegmentChoice>,
    /// Bandit: the round, and whether it explored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub round: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub explored: Option<bool>,
    /// The return of the episode (mean of the round's episodes, for a bandit round). serde_json
    /// writes a NaN (a diverged policy) as `null`; it reads back as NaN.
    #[serde(deserialize_with = "f64_or_null")]
    pub episode_return: f64,
}

fn f64_or_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

#[derive(Debug, thiserror::Error)]
pub enum StrategyError {
    #[error("unknown prompt strategy `{name}` (known: {known})")]
    UnknownName { name: String, known: String },
    #[error("prompt strategy setting `{field}` {why}")]
    Setting { field: &'static str, why: String },
    #[error("{0}")]
    Sampler(#[from] SamplerError),
}

/// Candidate windows of `h` steps in a demonstration of `t` steps, every `stride` steps, each
/// wholly inside it (a demonstration shorter than `h` gives its one, left-padded, window).
fn window_starts(t: usize, h: usize, stride: usize) -> impl Iterator<Item = usize> {
    (0..=t.saturating_sub(h)).step_by(stride.max(1))
}

impl BatchSampler<'_> {
    /// The demonstrations of task `task` (its prompt set).
    fn demos(&self, task: usize) -> &[pdt_data::Trajectory] {
        &self.task(task).prompts.trajectories
    }

    /// A `[1, J*H]` prompt of task `task` made of the given segments (J of them, each H steps,
    /// with this sampler's normalisation, return scale and timestep clip).
    pub fn prompt_from_choices(
        &self,
        task: usize,
        choices: &[SegmentChoice],
    ) -> Result<SegmentBatch, SamplerError> {
        let (h, j) = (self.config().prompt_length, self.config().prompt_episodes);
        let demos = self.demos(task);
        let bad =
            |why: String| Err(SamplerError::Task { task: self.task(task).id.to_string(), why });
        if choices.len() != j {
            return bad(format!("{} prompt segments given, the prompt has J = {j}", choices.len()));
        }
        let (ds, da) = (self.state_dim(), self.act_dim());
        let mut out = SegmentBatch::zeros(1, j * h, ds, da);
        for (seg, c) in choices.iter().enumerate() {
            let Some(traj) = demos.get(c.demo) else {
                return bad(format!("demonstration {} of {}", c.demo, demos.len()));
            };
            if c.start >= traj.len() {
                return bad(format!("start {} of a {}-step demonstration", c.start, traj.len()));
            }
            let slot = SegmentOut {
                states: &mut out.states[seg * h * ds..(seg + 1) * h * ds],
                actions: &mut out.actions[seg * h * da..(seg + 1) * h * da],
                returns_to_go: &mut out.returns_to_go[seg * h..(seg + 1) * h],
                timesteps: &mut out.timesteps[seg * h..(seg + 1) * h],
                mask: &mut out.mask[seg * h..(seg + 1) * h],
            };
            // Prompt returns-to-go are never zeroed (as in `write_prompts`).
            self.write_one(traj, c.start, h, slot);
        }
        Ok(out)
    }

    /// `random-segment`: per slot, a uniform demonstration and a uniform window inside it.
    pub fn random_segments(&self, task: usize, rng: &mut Rng) -> Vec<SegmentChoice> {
        let demos = self.demos(task);
        let h = self.config().prompt_length;
        (0..self.config().prompt_episodes)
            .map(|_| {
                let demo = rng.random_range(0..demos.len());
                let start = rng.random_range(0..=demos[demo].len().saturating_sub(h));
                SegmentChoice { demo, start }
            })
            .collect()
    }

    /// `best-return`: slot j takes the (j mod n)-th best demonstration by return (ties: the
    /// earlier one), at the reference's tail position `T - H - 1`.
    pub fn best_return_segments(&self, task: usize) -> Vec<SegmentChoice> {
        let demos = self.demos(task);
        let h = self.config().prompt_length;
        let returns: Vec<f64> =
            demos.iter().map(|t| t.rewards.iter().map(|&r| r as f64).sum()).collect();
        let mut order: Vec<usize> = (0..demos.len()).collect();
        // Stable: equal returns keep demonstration order.
        order.sort_by(|&a, &b| returns[b].total_cmp(&returns[a]));
        (0..self.config().prompt_episodes)
            .map(|j| {
                let demo = order[j % order.len()];
                SegmentChoice { demo, start: demos[demo].len().saturating_sub(h + 1) }
            })
            .collect()
    }

    /// Every candidate segment of task `task`: windows of H steps every `stride` steps of each
    /// demonstration, demonstration by demonstration.
    pub fn candidate_segments(&self, task: usize, stride: usize) -> Vec<SegmentChoice> {
        let h = self.config().prompt_length;
        self.demos(task)
            .iter()
            .enumerate()
            .flat_map(|(demo, t)| {
                window_starts(t.len(), h, stride).map(move |start| SegmentChoice { demo, start })
            })
            .collect()
    }

    /// `nearest-start`: the J candidate segments whose first states are nearest (Euclidean, in
    /// the normalised state space) the raw start observation `obs`, nearest first; ties keep
    /// candidate order. Fewer candidates than J repeat from the nearest.
    pub fn nearest_start_segments(
        &self,
        task: usize,
        obs: &[f32],
        stride: usize,
    ) -> Result<Vec<SegmentChoice>, SamplerError> {
        let ds = self.state_dim();
        if obs.len() != ds {
            return Err(SamplerError::Task {
                task: self.task(task).id.to_string(),
                why: format!("start observation has {} values, the states have {ds}", obs.len()),
            });
        }
        let norm = self.norm();
        let z: Vec<f64> = obs.iter().enumerate().map(|(j, &x)| norm.apply(j, x) as f64).collect();
        let demos = self.demos(task);
        let mut scored: Vec<(f64, SegmentChoice)> = self
            .candidate_segments(task, stride)
            .into_iter()
            .map(|c| {
                let first = demos[c.demo].obs(c.start);
                let d2 = first
                    .iter()
                    .enumerate()
                    .map(|(j, &x)| (norm.apply(j, x) as f64 - z[j]).powi(2))
                    .sum::<f64>();
                (d2, c)
            })
            .collect();
        scored.sort_by(|a, b| a.0.total_cmp(&b.0));
        let j = self.config().prompt_episodes;
        Ok((0..j).map(|i| scored[i % scored.len()].1).collect())
    }
}

/// Which config a sampler for a strategy needs, checked against the model's positions.
pub fn check_fits(
    strategy: &PromptStrategy,
    trained: &SamplerConfig,
    n_positions: usize,
) -> Result<SamplerConfig, StrategyError> {
    strategy.validate()?;
    let cfg = strategy.sampler_config(trained);
    cfg.validate(n_positions).map_err(|e| match e {
        SamplerError::Config { field: "k", why } => StrategyError::Setting {
            field: "episodes x length",
            why: format!(
                "(test-time prompt J x H = {} x {}) does not fit: {why}",
                cfg.prompt_episodes, cfg.prompt_length
            ),
        },
        other => StrategyError::Sampler(other),
    })?;
    Ok(cfg)
}
