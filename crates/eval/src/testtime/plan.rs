//! The tasks of one evaluation planned as the reference evaluation plans them (each task's prompt,
//! then its episodes' reset seeds: [`plan_task`]), and what an evaluation of a split needs of its
//! run ([`SplitEval`]). Every test time plans its tasks this way, so a strategy, an adaptation and
//! the reference rule meet the same start states, and their returns compare episode by episode.

use super::TestTimeError;
use crate::{summarise, EpisodePrompts, EpisodeRecord, EvalError, EvalSettings, EvalTask};
use crate::{GivenPrompts, TaskResult};
use pdt_data::{MultiTaskDataset, TaskData};
use pdt_envs::EnvFamily;
use pdt_model::PromptDt;
use pdt_prompt::strategy::check_fits;
use pdt_prompt::{BatchSampler, PromptStrategy, Rng, SamplerConfig, SegmentBatch, StateNorm};
use pdt_rundir::config::Method;
use rand::RngCore;

/// What an evaluation draws for one task: the prompt its episodes share and their reset seeds.
#[derive(Debug, Clone)]
pub struct TaskPlan {
    /// `cheetah_vel-2`
    pub name: String,
    /// Task index in its family.
    pub index: usize,
    /// `None` for the methods without a prompt.
    pub prompt: Option<SegmentBatch>,
    /// Reset seed of each episode.
    pub seeds: Vec<u64>,
}

/// Draws task `i`'s prompt (once per task and evaluation call, shared by its episodes, as the
/// reference does), then its episodes' seeds, from `rng`.
pub fn plan_task(
    method: Method,
    sampler: &BatchSampler,
    data: &MultiTaskDataset,
    i: usize,
    episodes: usize,
    rng: &mut Rng,
) -> TaskPlan {
    let t = &data.tasks[i];
    let prompt = sampler.eval_prompt(i, rng);
    let seeds = (0..episodes).map(|_| rng.next_u64()).collect();
    TaskPlan {
        name: t.id.to_string(),
        index: t.id.index,
        prompt: method.uses_prompt().then_some(prompt),
        seeds,
    }
}

/// What an evaluation of one split needs of its run: the model and the evaluation's settings, the
/// split's data with the run's sampling settings, the method, the episodes per task, and the
/// family that makes each task's environments.
pub struct SplitEval<'a> {
    pub model: &'a PromptDt,
    /// `model`'s variables, where an adaptation may change them for a task's episodes (full
    /// fine-tuning, `[eval.adapt] kind = "full"`: changed per task and restored bit for bit after
    /// its episodes); `None`: that adaptation is refused.
    pub weights: Option<&'a tch::nn::VarStore>,
    pub settings: &'a EvalSettings,
    pub data: &'a MultiTaskDataset,
    /// The run's sampler settings; a strategy's prompt shape is cut from them.
    pub sampler_cfg: &'a SamplerConfig,
    pub norm: &'a StateNorm,
    /// The model's positions, which a prompt and history must fit.
    pub n_positions: usize,
    pub method: Method,
    /// Episodes per task (`eval.episodes`).
    pub episodes: usize,
    pub family: &'a dyn EnvFamily,
    /// The run set its G* itself (`eval.target_return`): every task is conditioned on it, a
    /// task's own target (`EnvFamily::task_target_return`) included.
    pub run_target_set: bool,
}

impl SplitEval<'_> {
    /// The sampler over the split's data with the run's settings (the reference rule's).
    pub fn reference_sampler(&self) -> Result<BatchSampler<'_>, TestTimeError> {
        self.sampler_with(self.sampler_cfg.clone())
    }

    /// The sampler `strategy` picks its prompts with (its prompt shape checked against the
    /// model's positions); draws nothing.
    pub fn strategy_sampler(
        &self,
        strategy: &PromptStrategy,
    ) -> Result<BatchSampler<'_>, TestTimeError> {
        self.sampler_with(check_fits(strategy, self.sampler_cfg, self.n_positions)?)
    }

    fn sampler_with(&self, cfg: SamplerConfig) -> Result<BatchSampler<'_>, TestTimeError> {
        let tasks: Vec<&TaskData> = self.data.tasks.iter().collect();
        Ok(BatchSampler::new(cfg, &tasks, self.norm.clone(), self.n_positions)?)
    }

    /// Task `i` planned as the reference evaluation plans it, with the reference sampler
    /// `reference` (draws from `rng`).
    pub fn plan(&self, reference: &BatchSampler<'_>, i: usize, rng: &mut Rng) -> TaskPlan {
        plan_task(self.method, reference, self.data, i, self.episodes, rng)
    }

    /// Every task of the split planned as the reference evaluation plans it (draws from `rng`).
    pub fn plan_tasks(&self, rng: &mut Rng) -> Result<Vec<TaskPlan>, TestTimeError> {
        let reference = self.reference_sampler()?;
        Ok((0..self.data.tasks.len()).map(|i| self.plan(&reference, i, rng)).collect())
    }

    /// A task's evaluation: an episode per reset seed, and its prompt (`None`: the evaluation's
    /// given prompts, or none for the methods without a prompt). Its environments are made by the
    /// family when [`SplitEval::evaluate`] starts, all tasks' at once.
    pub fn task(&self, plan: &TaskPlan, seeds: &[u64], prompt: Option<SegmentBatch>) -> EvalTask {
        let (name, index, seeds) = (plan.name.clone(), plan.index, seeds.to_vec());
        let target_return = self.task_target_return(index);
        EvalTask { name, index, envs: Vec::new(), seeds, prompt, target_return }
    }

    /// The G* task `index` (the family's) is conditioned on where it differs from the run's: its
    /// own (a suite's `[[tasks]] target_return`) unless the run set one for every task.
    pub fn task_target_return(&self, index: usize) -> Option<f32> {
        if self.run_target_set {
            return None;
        }
        self.family.task_target_return(index)
    }

    /// Plays the episodes of `tasks` (made by [`SplitEval::task`]) with `model` in the family's
    /// environments ([`crate::evaluate_in`]), each episode's prompt chosen by `chooser` or the
    /// prompts `given` where set.
    pub fn evaluate(
        &self,
        model: &PromptDt,
        tasks: Vec<EvalTask>,
        chooser: Option<&mut dyn EpisodePrompts>,
        given: Option<GivenPrompts<'_>>,
    ) -> Result<Vec<EpisodeRecord>, EvalError> {
        crate::evaluate_in(self.family, model, tasks, self.settings, chooser, given)
    }
}

/// Per planned task, the summary of its episodes (`task_index`: the plan's position).
pub fn summarise_plans(plans: &[TaskPlan], episodes: &[EpisodeRecord]) -> Vec<TaskResult> {
    plans
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let mine: Vec<&EpisodeRecord> = episodes.iter().filter(|e| e.task_index == k).collect();
            summarise(&p.name, p.index, &mine)
        })
        .collect()
}
