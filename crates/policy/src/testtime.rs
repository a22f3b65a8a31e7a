//! A policy's test time: the prompt a strategy picks for an episode, a task's `bandit`, and an
//! adaptation to a task (`promptdt serve`, the Python `Policy`). Each builds the task's sampler
//! from the run's prompt sets and calls [`pdt_eval::testtime`], the one owner of test time.

use crate::{Policy, PolicyError};
use pdt_eval::testtime::{self, ChosenPrompt, TaskAdaptation, TaskBandit, TestTimeError};
use pdt_prompt::bandit::BanditChoice;
use pdt_prompt::{PromptStrategy, Rng};
use pdt_rundir::config::{Adaptation, TestTime};
use rand::{RngCore, SeedableRng};

impl From<TestTimeError> for PolicyError {
    fn from(e: TestTimeError) -> Self {
        match e {
            TestTimeError::Input(m) => PolicyError::Input(m),
            TestTimeError::Failed(m) => PolicyError::Invalid(m),
            TestTimeError::Sampler(e) => PolicyError::Sampler(e),
            TestTimeError::Strategy(e) => PolicyError::Strategy(e),
            TestTimeError::Env(e) => PolicyError::Env(e),
            TestTimeError::Eval(e) => PolicyError::Eval(e),
        }
    }
}

impl Policy {
    /// Adapts to task `task` from its demonstrations as `test_time` says (an `[eval.adapt]`
    /// adaptation, starting from the prompt its strategy picks); `seed` seeds the start prompt's
    /// draw, the adaptation and its probe batch. A test time without such an adaptation (the
    /// adaptations of a learner's own weights included: a policy acts with the weights as saved)
    /// is refused.
    pub fn adapt(
        &self,
        task: usize,
        seed: u64,
        test_time: &TestTime,
    ) -> Result<TaskAdaptation, PolicyError> {
        let (strategy, cfg) = match test_time {
            TestTime::Adapt { from, adaptation: Adaptation::Prompt(cfg) } => (from, cfg),
            other => {
                return Err(PolicyError::Input(format!(
                    "a policy adapts with soft-prompt, ptdt or lora, not {}",
                    other.adaptation().map_or("no adaptation", Adaptation::name)
                )))
            }
        };
        testtime::check_adaptable(self.method, strategy, cfg)?;
        let sampler = self.task_sampler(task, Some(strategy))?;
        let mut rng = Rng::seed_from_u64(seed);
        let start = testtime::start_prompt(&sampler, 0, strategy, None, &mut rng)?;
        let mut arng = Rng::seed_from_u64(rng.next_u64());
        let name = format!("{}-{task}", self.env);
        let t = testtime::AdaptTask {
            model: &self.model,
            sampler: &sampler,
            index: 0,
            name: &name,
            cfg,
            // Full fine-tuning is refused: a policy acts with the weights as saved.
            weights: None,
            probe_seed: rng.next_u64(),
        };
        Ok(testtime::adapt_task(&t, &start, None, &mut arng)?)
    }

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
        Ok(testtime::choose_prompt(&sampler, 0, strategy, &mut rng, obs)?)
    }

    /// A fresh `bandit` over task `task`'s candidate segments, its choices seeded by `seed`.
    pub fn task_bandit(
        &self,
        task: usize,
        seed: u64,
        strategy: &PromptStrategy,
    ) -> Result<TaskBandit, PolicyError> {
        if pdt_prompt::bandit::SegmentBandit::needs_rounds(&strategy.bandit) {
            // A served or Python bandit plays as many rounds as episodes come: no share of them
            // is known, so a schedule over one would be silently another schedule.
            return Err(PolicyError::Input(format!(
                "task {task}: bandit.explore_fraction needs the number of rollouts, which only an \
                 evaluation knows (`promptdt eval`); use bandit.epsilon_decay here"
            )));
        }
        let sampler = self.task_sampler(task, Some(strategy))?;
        Ok(TaskBandit::new(&sampler, 0, task, seed, strategy)?)
    }

    /// The next episode's prompt of `bandit` (one of this policy's, [`Policy::task_bandit`]) and
    /// the arms it pulled (report the episode's return with `TaskBandit::update`).
    pub fn bandit_prompt(
        &self,
        bandit: &mut TaskBandit,
    ) -> Result<(ChosenPrompt, BanditChoice), PolicyError> {
        let sampler = self.task_sampler(bandit.task, Some(bandit.strategy()))?;
        Ok(bandit.choose(&sampler, 0)?)
    }
}
