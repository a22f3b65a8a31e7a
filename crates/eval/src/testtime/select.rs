//! Selection: the prompt a test-time [`PromptStrategy`] picks for a task's episode (`reference`,
//! `random-segment`, `best-return`, `nearest-start`; [`choose_prompt`]), the `bandit`'s state
//! across a task's episodes ([`TaskBandit`], which learns from the returns its owner reports),
//! and the evaluator's per-episode choice at reset ([`NearestStart`]), each logged as a
//! [`PromptPick`]. The strategies' algorithms are `pdt_prompt`'s (the selectors on
//! `BatchSampler`, the bandit); this is where every caller (`promptdt eval`, serve, Python)
//! takes them from.

use super::TestTimeError;
use crate::{EpisodePrompts, EvalError};
use pdt_prompt::bandit::{BanditChoice, SegmentBandit};
use pdt_prompt::{
    BatchSampler, PromptPick, PromptStrategy, PromptStrategyKind, Rng, SegmentBatch, SegmentChoice,
};
use rand::SeedableRng;

/// A prompt chosen by a strategy, with the segments it is made of (empty for `reference`, whose
/// draw is the evaluation's `BatchSampler::eval_prompt`).
#[derive(Debug, Clone)]
pub struct ChosenPrompt {
    pub prompt: SegmentBatch,
    pub segments: Vec<SegmentChoice>,
}

/// The prompt of an episode of task `index` (of `sampler`'s tasks) under `strategy` (not
/// `bandit`: see [`TaskBandit`]); `reference` and `random-segment` draw from `rng`, `obs` (the
/// episode's raw first observation) is what `nearest-start` is nearest to.
pub fn choose_prompt(
    sampler: &BatchSampler<'_>,
    index: usize,
    strategy: &PromptStrategy,
    rng: &mut Rng,
    obs: Option<&[f32]>,
) -> Result<ChosenPrompt, TestTimeError> {
    let segments = match strategy.strategy {
        PromptStrategyKind::Reference => {
            return Ok(ChosenPrompt { prompt: sampler.eval_prompt(index, rng), segments: vec![] })
        }
        PromptStrategyKind::RandomSegment => sampler.random_segments(index, rng),
        PromptStrategyKind::BestReturn => sampler.best_return_segments(index),
        PromptStrategyKind::NearestStart => {
            let obs = obs.ok_or_else(|| {
                TestTimeError::Input(
                    "prompt strategy `nearest-start` needs the episode's first observation".into(),
                )
            })?;
            let stride = strategy.stride_for(sampler.config().prompt_length);
            sampler.nearest_start_segments(index, obs, stride)?
        }
        PromptStrategyKind::Bandit => {
            return Err(TestTimeError::Input(
                "prompt strategy `bandit` learns across a task's episodes, so it is kept per \
                 task: `Policy::task_bandit` (Python: `Policy.prompt_bandit`; serve keeps one per \
                 task; `promptdt eval --prompt-strategy bandit` one per evaluation)"
                    .into(),
            ))
        }
    };
    let prompt = sampler.prompt_from_choices(index, &segments)?;
    Ok(ChosenPrompt { prompt, segments })
}

/// A `bandit` over one task's candidate segments, its generator seeded once.
#[derive(Debug, Clone)]
pub struct TaskBandit {
    pub task: usize,
    strategy: PromptStrategy,
    bandit: SegmentBandit,
    rng: Rng,
}

impl TaskBandit {
    /// A fresh bandit over task `task`'s candidate segments (task `index` of `sampler`'s, which
    /// is `strategy`'s sampler), its choices seeded by `seed`.
    pub fn new(
        sampler: &BatchSampler<'_>,
        index: usize,
        task: usize,
        seed: u64,
        strategy: &PromptStrategy,
    ) -> Result<Self, TestTimeError> {
        let h = sampler.config().prompt_length;
        let arms = sampler.candidate_segments(index, strategy.stride_for(h));
        let j = sampler.config().prompt_episodes;
        let bandit = SegmentBandit::new(strategy.bandit.clone(), arms, j)
            .ok_or_else(|| TestTimeError::Input(format!("task {task}: no candidate segment")))?;
        Ok(Self { task, strategy: strategy.clone(), bandit, rng: Rng::seed_from_u64(seed) })
    }

    /// This episode's prompt (from task `index` of `sampler`, the strategy's sampler) and the
    /// arms it pulled (report them with [`TaskBandit::update`]).
    pub fn choose(
        &mut self,
        sampler: &BatchSampler<'_>,
        index: usize,
    ) -> Result<(ChosenPrompt, BanditChoice), TestTimeError> {
        let choice = self.bandit.choose(&mut self.rng);
        let segments = self.bandit.segments(&choice);
        let prompt = sampler.prompt_from_choices(index, &segments)?;
        Ok((ChosenPrompt { prompt, segments }, choice))
    }

    /// The return of an episode that used `choice`.
    pub fn update(&mut self, choice: &BanditChoice, episode_return: f64) {
        self.bandit.update(choice, &[episode_return]);
    }

    pub fn strategy(&self) -> &PromptStrategy {
        &self.strategy
    }
}

/// The log line of a strategy's choice for `task`'s episode `episode` (the first of a bandit
/// round `(round, explored)`); its return is filled in when the episodes end.
pub fn pick(
    task: &str,
    episode: usize,
    segments: Vec<SegmentChoice>,
    round: Option<(usize, bool)>,
) -> PromptPick {
    PromptPick {
        task: task.to_string(),
        episode,
        segments,
        round: round.map(|r| r.0),
        explored: round.map(|r| r.1),
        episode_return: f64::NAN,
    }
}

/// `nearest-start`'s choice at each episode's reset in an evaluation ([`crate::evaluate_with`]),
/// logged with the task's position.
pub struct NearestStart<'a> {
    sampler: &'a BatchSampler<'a>,
    stride: usize,
    names: &'a [String],
    picks: Vec<(PromptPick, usize)>,
}

impl<'a> NearestStart<'a> {
    /// The chooser over `sampler`'s tasks (named `names`, in its order) at `stride`.
    pub fn new(sampler: &'a BatchSampler<'a>, stride: usize, names: &'a [String]) -> Self {
        Self { sampler, stride, names, picks: Vec::new() }
    }

    /// The choices made, each with its task's position.
    pub fn into_picks(self) -> Vec<(PromptPick, usize)> {
        self.picks
    }
}

impl EpisodePrompts for NearestStart<'_> {
    fn at_reset(
        &mut self,
        task: usize,
        episode: usize,
        obs: &[f32],
    ) -> Result<SegmentBatch, EvalError> {
        let name = || self.names.get(task).cloned().unwrap_or_default();
        let fail =
            |e: pdt_prompt::SamplerError| EvalError::Setup { task: name(), why: e.to_string() };
        let segments = self.sampler.nearest_start_segments(task, obs, self.stride).map_err(fail)?;
        let prompt = self.sampler.prompt_from_choices(task, &segments).map_err(fail)?;
        self.picks.push((pick(&name(), episode, segments, None), task));
        Ok(prompt)
    }
}
