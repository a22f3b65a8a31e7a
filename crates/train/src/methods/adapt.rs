//! Evaluation with an evaluation-time adaptation (`[eval.adapt]`, `promptdt eval --adapt`;
//! `docs/prompt-control.md`): per test task, the prompt the strategy picks (one per task:
//! `reference`, `random-segment` or `best-return`) is the starting point; soft prompt tuning,
//! the Prompt-Tuning DT update or LoRA adapt from the task's demonstrations, the backbone frozen;
//! then the task's episodes run with the result.
//!
//! Reset seeds are the reference evaluation's (tasks planned by `plan_task`, as the strategies
//! do), so an adapted evaluation meets the same start states as Prompt-DT. The adaptation draws
//! from its own generator, seeded from the same evaluation stream after the plans.

use super::planned::{eval_task, plan_tasks, strategy_sampler, summarise_plans};
use crate::error::RunError;
use crate::setup::Setup;
use pdt_data::MultiTaskDataset;
use pdt_eval::adapt::{AdaptConfig, AdaptKind, AdaptLog, PromptScore};
use pdt_eval::{
    evaluate, evaluate_given, EpisodeRecord, EvalError, EvalSettings, EvalTask, GivenPrompts,
    TaskResult,
};
use pdt_model::{PrefixCache, PromptDt};
use pdt_policy::adapt::{adapt_task, check_adaptable, start_prompt, AdaptTask};
use pdt_policy::{Adapted, TaskPlan};
use pdt_prompt::{PromptStrategy, Rng, SegmentBatch};
use rand::{RngCore, SeedableRng};

/// An adapted evaluation's per-task results and what each adaptation did.
pub(crate) struct AdaptedEval {
    pub(crate) results: Vec<TaskResult>,
    pub(crate) log: Vec<AdaptLog>,
}

/// Evaluates every task of `data` after adapting to each from its demonstrations.
pub(crate) fn evaluate_adapted(
    model: &PromptDt,
    setup: &Setup,
    data: &MultiTaskDataset,
    settings: &EvalSettings,
    strategy: &PromptStrategy,
    cfg: &AdaptConfig,
    rng: &mut Rng,
) -> Result<AdaptedEval, RunError> {
    let method = setup.cfg.run.method;
    check_adaptable(method, strategy, cfg)?;
    let plans = plan_tasks(setup, data, rng)?;
    let mut arng = Rng::seed_from_u64(rng.next_u64());
    // The probe batches (loss before/after) come from a generator of their own, so they are the
    // same whichever adaptation runs: the logs of two adaptations compare task by task.
    let probe_seed = rng.next_u64();
    let sampler = strategy_sampler(setup, data, strategy)?;
    let make = |plan: &TaskPlan, seeds: &[u64], prompt: Option<SegmentBatch>| {
        eval_task(setup, plan, seeds, prompt)
    };
    let mut log = Vec::with_capacity(plans.len());
    let mut all: Vec<EpisodeRecord> = Vec::new();
    // Soft prompt and PTDT results go through one batched evaluation of all tasks; LoRA's
    // adapters differ per task, so each task runs alone with its own.
    let mut prefixes: Vec<PrefixCache> = Vec::new();
    let mut tuned: Vec<SegmentBatch> = Vec::new();
    for (i, plan) in plans.iter().enumerate() {
        let start = start_prompt(&sampler, i, strategy, plan.prompt.clone(), &mut arng)?;
        let task = AdaptTask {
            model,
            sampler: &sampler,
            index: i,
            name: &plan.name,
            cfg,
            probe_seed: probe_seed.wrapping_add(i as u64),
        };
        let episodes = cfg.ptdt.score_episodes;
        let mut online = ReturnScore { model, settings, plan, make: &make, episodes };
        let a = adapt_task(&task, &start, Some(&mut online), &mut arng)?;
        log.push(a.log.clone());
        match a.adapted {
            Adapted::Tokens(_) => prefixes.push(a.prefix(model)),
            Adapted::Prompt(p) => tuned.push(p),
            Adapted::Lora { .. } => {
                let given = GivenPrompts { prefix: a.prefix(model), lora: a.lora() };
                let mut eps =
                    evaluate_given(model, vec![make(plan, &plan.seeds, None)?], settings, given)?;
                eps.iter_mut().for_each(|e| e.task_index = i);
                all.extend(eps);
            }
        }
    }
    match cfg.kind {
        AdaptKind::SoftPrompt => {
            let refs: Vec<&PrefixCache> = prefixes.iter().collect();
            let prefix = PrefixCache::cat(&refs)
                .ok_or_else(|| RunError::Internal("tuned prompts of different lengths".into()))?;
            let tasks =
                plans.iter().map(|p| make(p, &p.seeds, None)).collect::<Result<Vec<_>, _>>()?;
            all = evaluate_given(model, tasks, settings, GivenPrompts { prefix, lora: None })?;
        }
        AdaptKind::Ptdt => {
            let tasks = plans
                .iter()
                .zip(tuned)
                .map(|(p, t)| make(p, &p.seeds, Some(t)))
                .collect::<Result<Vec<_>, _>>()?;
            all = evaluate(model, tasks, settings)?;
        }
        _ => {}
    }
    Ok(AdaptedEval { results: summarise_plans(&plans, &all), log })
}

/// Builds a task's evaluation from its plan, the episodes' seeds and its prompt.
type MakeTask<'a> =
    dyn Fn(&TaskPlan, &[u64], Option<SegmentBatch>) -> Result<EvalTask, RunError> + 'a;

/// The online score: the mean return of `episodes` episodes per candidate in the task's
/// environment, every candidate on the same reset seeds (drawn per call, apart from the
/// evaluation's), all candidates' episodes stepped together.
struct ReturnScore<'a> {
    model: &'a PromptDt,
    settings: &'a EvalSettings,
    plan: &'a TaskPlan,
    make: &'a MakeTask<'a>,
    episodes: usize,
}

impl PromptScore for ReturnScore<'_> {
    fn scores(
        &mut self,
        candidates: &[SegmentBatch],
        rng: &mut Rng,
    ) -> Result<Vec<f64>, EvalError> {
        let seeds: Vec<u64> = (0..self.episodes).map(|_| rng.next_u64()).collect();
        let setup_err =
            |e: RunError| EvalError::Setup { task: self.plan.name.clone(), why: e.to_string() };
        let tasks = candidates
            .iter()
            .map(|c| (self.make)(self.plan, &seeds, Some(c.clone())))
            .collect::<Result<Vec<_>, _>>()
            .map_err(setup_err)?;
        let eps = evaluate(self.model, tasks, self.settings)?;
        Ok((0..candidates.len())
            .map(|k| {
                let r: Vec<f64> =
                    eps.iter().filter(|e| e.task_index == k).map(|e| e.episode_return).collect();
                r.iter().sum::<f64>() / r.len().max(1) as f64
            })
            .collect())
    }
}
