//! Test-time prompt strategies for an acting policy (`promptdt serve`, the Python `Policy`):
//! the prompt of one episode of a task, chosen by a [`PromptStrategy`] as `promptdt eval` chooses
//! it (`pdt_prompt::strategy`), and the `bandit`'s state across a task's episodes
//! ([`TaskBandit`]), which learns from the returns its owner reports when an episode ends.

use crate::{Policy, PolicyError};
use pdt_prompt::bandit::{BanditChoice, SegmentBandit};
use pdt_prompt::{PromptStrategy, PromptStrategyKind, Rng, SegmentBatch, SegmentChoice};
use rand::SeedableRng;

/// A prompt chosen by a strategy, with the segments it is made of (empty for `reference`, whose
/// draw is the evaluation's `BatchSampler::eval_prompt`).
#[derive(Debug, Clone)]
pub struct ChosenPrompt {
    pub prompt: SegmentBatch,
    pub segments: Vec<SegmentChoice>,
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
    /// This episode's prompt and the arms it pulled (report them with [`TaskBandit::update`]).
    pub fn choose(&mut self, policy: &Policy) -> Result<(ChosenPrompt, BanditChoice), PolicyError> {
        let sampler = policy.task_sampler(self.task, Some(&self.strategy))?;
        let choice = self.bandit.choose(&mut self.rng);
        let segments = self.bandit.segments(&choice);
        let prompt = sampler.prompt_from_choices(0, &segments)?;
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

impl Policy {
    /// The prompt of an episode of task `task` under `strategy` (not `bandit`: see
    /// [`Policy::task_bandit`]); `seed` seeds `reference` and `random-segment`, `obs` (the
    /// episode's raw first observation) is what `nearest-start` is nearest to.
    pub fn strategy_prompt(
        &self,
        task: usize,
        seed: u64,
        strategy: &PromptStrategy,
        obs: Option<&[f32]>,
    ) -> Result<ChosenPrompt, PolicyError> {
        let sampler = self.task_sampler(task, Some(strategy))?;
        let mut rng = Rng::seed_from_u64(seed);
        let segments =
            match strategy.strategy {
                PromptStrategyKind::Reference => {
                    return Ok(ChosenPrompt {
                        prompt: sampler.eval_prompt(0, &mut rng),
                        segments: vec![],
                    })
                }
                PromptStrategyKind::RandomSegment => sampler.random_segments(0, &mut rng),
                PromptStrategyKind::BestReturn => sampler.best_return_segments(0),
                PromptStrategyKind::NearestStart => {
                    let obs = obs.ok_or_else(|| {
                        PolicyError::Input(
                            "prompt strategy `nearest-start` needs the episode's first observation"
                                .into(),
                        )
                    })?;
                    let stride = strategy.stride_for(sampler.config().prompt_length);
                    sampler.nearest_start_segments(0, obs, stride)?
                }
                PromptStrategyKind::Bandit => return Err(PolicyError::Input(
                    "prompt strategy `bandit` learns across a task's episodes, so it is kept per \
                     task: `Policy::task_bandit` (Python: `Policy.prompt_bandit`; serve keeps one \
                     per task; `promptdt eval --prompt-strategy bandit` one per evaluation)"
                        .into(),
                )),
            };
        let prompt = sampler.prompt_from_choices(0, &segments)?;
        Ok(ChosenPrompt { prompt, segments })
    }

    /// A fresh `bandit` over task `task`'s candidate segments, its choices seeded by `seed`.
    pub fn task_bandit(
        &self,
        task: usize,
        seed: u64,
        strategy: &PromptStrategy,
    ) -> Result<TaskBandit, PolicyError> {
        if SegmentBandit::needs_rounds(&strategy.bandit) {
            // A served or Python bandit plays as many rounds as episodes come: no share of them
            // is known, so a schedule over one would be silently another schedule.
            return Err(PolicyError::Input(format!(
                "task {task}: bandit.explore_fraction needs the number of rollouts, which only an \
                 evaluation knows (`promptdt eval`); use bandit.epsilon_decay here"
            )));
        }
        let sampler = self.task_sampler(task, Some(strategy))?;
        let h = sampler.config().prompt_length;
        let arms = sampler.candidate_segments(0, strategy.stride_for(h));
        let j = sampler.config().prompt_episodes;
        let bandit = SegmentBandit::new(strategy.bandit.clone(), arms, j)
            .ok_or_else(|| PolicyError::Input(format!("task {task}: no candidate segment")))?;
        Ok(TaskBandit { task, strategy: strategy.clone(), bandit, rng: Rng::seed_from_u64(seed) })
    }
}
