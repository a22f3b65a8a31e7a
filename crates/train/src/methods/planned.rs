//! What the evaluations with a prompt strategy (`prompt_strategy.rs`) and with an adaptation
//! (`adapt.rs`) share: the tasks planned as the reference evaluation plans them (so their reset
//! seeds, and start states, are the reference's), the strategy's sampler over the tasks' data,
//! a task's evaluation built from its plan, and the per-task results of the episodes.

use crate::error::RunError;
use crate::setup::Setup;
use pdt_data::{MultiTaskDataset, TaskData};
use pdt_eval::{summarise, EpisodeRecord, EvalTask};
use pdt_prompt::strategy::check_fits;
use pdt_prompt::{BatchSampler, PromptStrategy, Rng, SegmentBatch};
use pdt_run::{plan_task, TaskPlan};
use pdt_rundir::TaskResult;

/// Every task of `data` planned as the reference evaluation plans it (draws from `rng`).
pub(crate) fn plan_tasks(
    setup: &Setup,
    data: &MultiTaskDataset,
    rng: &mut Rng,
) -> Result<Vec<TaskPlan>, RunError> {
    let (method, episodes) = (setup.cfg.run.method, setup.cfg.eval.episodes);
    let reference = setup.sampler(data)?;
    Ok((0..data.tasks.len())
        .map(|i| plan_task(method, &reference, data, i, episodes, rng))
        .collect())
}

/// The sampler `strategy` picks its prompts with (its prompt shape checked against the model's
/// positions); draws nothing.
pub(crate) fn strategy_sampler<'a>(
    setup: &Setup,
    data: &'a MultiTaskDataset,
    strategy: &PromptStrategy,
) -> Result<BatchSampler<'a>, RunError> {
    let rd = &setup.run_data;
    let cfg = check_fits(strategy, &rd.sampler_cfg, rd.model_cfg.n_positions)?;
    let tasks: Vec<&TaskData> = data.tasks.iter().collect();
    Ok(BatchSampler::new(cfg, &tasks, rd.norm.clone(), rd.model_cfg.n_positions)?)
}

/// A task's evaluation: an environment per reset seed, and its prompt (`None`: the evaluation's
/// given prompts, or the task's own).
pub(crate) fn eval_task(
    setup: &Setup,
    plan: &TaskPlan,
    seeds: &[u64],
    prompt: Option<SegmentBatch>,
) -> Result<EvalTask, RunError> {
    let envs = seeds.iter().map(|_| setup.family.make(plan.index)).collect::<Result<_, _>>()?;
    Ok(EvalTask { name: plan.name.clone(), index: plan.index, envs, seeds: seeds.to_vec(), prompt })
}

/// Per planned task, the summary of its episodes (`task_index`: the plan's position).
pub(crate) fn summarise_plans(plans: &[TaskPlan], episodes: &[EpisodeRecord]) -> Vec<TaskResult> {
    plans
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let mine: Vec<&EpisodeRecord> = episodes.iter().filter(|e| e.task_index == k).collect();
            summarise(&p.name, p.index, &mine)
        })
        .collect()
}
