//! Evaluation with a test-time prompt strategy other than the reference rule
//! (`[eval.prompt]`, `promptdt eval --prompt-strategy`; `docs/prompt-control.md`).
//!
//! Reset seeds are those of the reference evaluation: the tasks are planned as the reference
//! plans them (`plan_task`), and the strategy draws from its own generator, seeded from the same
//! evaluation stream after the plans. So a strategy and the reference rule meet the same start
//! states, and their returns compare episode by episode.

use super::planned::{eval_task, plan_tasks, strategy_sampler, summarise_plans};
use crate::error::RunError;
use crate::setup::Setup;
use pdt_data::MultiTaskDataset;
use pdt_eval::{
    evaluate, evaluate_with, EpisodePrompts, EpisodeRecord, EvalError, EvalSettings, EvalTask,
    TaskResult,
};
use pdt_model::PromptDt;
use pdt_policy::TaskPlan;
use pdt_prompt::bandit::SegmentBandit;
use pdt_prompt::{
    BatchSampler, PromptPick, PromptStrategy, PromptStrategyKind, Rng, SegmentBatch, SegmentChoice,
};
use rand::{RngCore, SeedableRng};

/// What an evaluation with a strategy gives: per-task results and the strategy's choices.
pub(crate) struct StrategyEval {
    pub(crate) results: Vec<TaskResult>,
    pub(crate) picks: Vec<PromptPick>,
}

/// Evaluates every task of `data` with `strategy`, all tasks' episodes stepped together (the
/// bandit: one round of `bandit.episodes_per_round` episodes per task at a time).
pub(crate) fn evaluate_strategy(
    model: &PromptDt,
    setup: &Setup,
    data: &MultiTaskDataset,
    settings: &EvalSettings,
    strategy: &PromptStrategy,
    rng: &mut Rng,
) -> Result<StrategyEval, RunError> {
    let method = setup.cfg.run.method;
    if !method.uses_prompt() {
        return Err(RunError::Invalid(format!(
            "prompt strategy `{}`: {} takes no prompt",
            strategy.strategy,
            method.name()
        )));
    }
    let plans = plan_tasks(setup, data, rng)?;
    let mut srng = Rng::seed_from_u64(rng.next_u64());
    let sampler = strategy_sampler(setup, data, strategy)?;
    let stride = strategy.stride_for(sampler.config().prompt_length);
    let envs_of = |plan: &TaskPlan, seeds: &[u64], prompt: Option<SegmentBatch>| {
        eval_task(setup, plan, seeds, prompt)
    };
    let summarise_all = |eps: &[EpisodeRecord]| summarise_plans(&plans, eps);
    match strategy.strategy {
        PromptStrategyKind::Reference
        | PromptStrategyKind::RandomSegment
        | PromptStrategyKind::BestReturn => {
            // One prompt per task, shared by its episodes (as the reference shares its draw).
            let mut picks = Vec::new();
            let mut eval_tasks = Vec::with_capacity(plans.len());
            for (i, plan) in plans.iter().enumerate() {
                let prompt = match strategy.strategy {
                    PromptStrategyKind::Reference => sampler.eval_prompt(i, &mut srng),
                    kind => {
                        let segments = if kind == PromptStrategyKind::RandomSegment {
                            sampler.random_segments(i, &mut srng)
                        } else {
                            sampler.best_return_segments(i)
                        };
                        let p = sampler.prompt_from_choices(i, &segments)?;
                        picks.push(pick(&plan.name, 0, segments, None));
                        p
                    }
                };
                eval_tasks.push(envs_of(plan, &plan.seeds, Some(prompt))?);
            }
            let eps = evaluate(model, eval_tasks, settings)?;
            let results = summarise_all(&eps);
            for p in &mut picks {
                if let Some(r) = results.iter().find(|r| r.task == p.task) {
                    p.episode_return = r.return_mean;
                }
            }
            Ok(StrategyEval { results, picks })
        }
        PromptStrategyKind::NearestStart => {
            let eval_tasks =
                plans.iter().map(|p| envs_of(p, &p.seeds, None)).collect::<Result<Vec<_>, _>>()?;
            let names: Vec<String> = plans.iter().map(|p| p.name.clone()).collect();
            let mut chooser =
                NearestStart { sampler: &sampler, stride, names: &names, picks: vec![] };
            let eps = evaluate_with(model, eval_tasks, settings, Some(&mut chooser))?;
            let mut picks = chooser.picks;
            for (p, k) in picks.iter_mut() {
                let ep = eps.iter().filter(|e| e.task_index == *k).nth(p.episode);
                p.episode_return = ep.map_or(f64::NAN, |e| e.episode_return);
            }
            Ok(StrategyEval {
                results: summarise_all(&eps),
                picks: picks.into_iter().map(|(p, _)| p).collect(),
            })
        }
        PromptStrategyKind::Bandit => {
            bandit_rounds(model, &sampler, &plans, settings, strategy, stride, &mut srng, &envs_of)
                .map(|(eps, picks)| StrategyEval { results: summarise_all(&eps), picks })
        }
    }
}

fn pick(
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

/// `nearest-start`'s choice at each episode's reset, logged with the task's position.
struct NearestStart<'a> {
    sampler: &'a BatchSampler<'a>,
    stride: usize,
    names: &'a [String],
    picks: Vec<(PromptPick, usize)>,
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

/// Builds a task's evaluation from its plan, the episodes' seeds and its prompt.
type MakeTask<'a> =
    dyn Fn(&TaskPlan, &[u64], Option<SegmentBatch>) -> Result<EvalTask, RunError> + 'a;

/// The bandit's rounds: each round, every task's bandit picks its arms, the tasks' round episodes
/// run together, and each bandit learns its episodes' returns. Returns every episode (task
/// positions as in `plans`, episodes in order) and one pick per task and round.
#[allow(clippy::too_many_arguments)] // the evaluation's pieces, from one caller
fn bandit_rounds(
    model: &PromptDt,
    sampler: &BatchSampler<'_>,
    plans: &[TaskPlan],
    settings: &EvalSettings,
    strategy: &PromptStrategy,
    stride: usize,
    rng: &mut Rng,
    envs_of: &MakeTask<'_>,
) -> Result<(Vec<EpisodeRecord>, Vec<PromptPick>), RunError> {
    let j = sampler.config().prompt_episodes;
    let mut bandits = plans
        .iter()
        .enumerate()
        .map(|(i, p)| {
            SegmentBandit::new(strategy.bandit.clone(), sampler.candidate_segments(i, stride), j)
                .ok_or_else(|| RunError::Invalid(format!("task {}: no candidate segment", p.name)))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let per_round = strategy.bandit.episodes_per_round;
    let episodes = plans.first().map_or(0, |p| p.seeds.len());
    // An epsilon schedule over a share of the rollouts (`explore_fraction`) needs their number.
    for b in &mut bandits {
        b.plan_rounds(episodes.div_ceil(per_round));
    }
    let (mut all, mut picks) = (Vec::new(), Vec::new());
    for (round, first) in (0..episodes).step_by(per_round).enumerate() {
        let last = (first + per_round).min(episodes);
        let mut choices = Vec::with_capacity(plans.len());
        let mut tasks = Vec::with_capacity(plans.len());
        for (i, plan) in plans.iter().enumerate() {
            let c = bandits[i].choose(rng);
            let segments = bandits[i].segments(&c);
            let prompt = sampler.prompt_from_choices(i, &segments)?;
            tasks.push(envs_of(plan, &plan.seeds[first..last], Some(prompt))?);
            picks.push(pick(&plan.name, first, segments, Some((round, c.explored))));
            choices.push(c);
        }
        let eps = evaluate(model, tasks, settings)?;
        let n = picks.len();
        for (i, c) in choices.iter().enumerate() {
            let returns: Vec<f64> =
                eps.iter().filter(|e| e.task_index == i).map(|e| e.episode_return).collect();
            bandits[i].update(c, &returns);
            let pick = &mut picks[n - plans.len() + i];
            pick.episode_return = returns.iter().sum::<f64>() / returns.len().max(1) as f64;
        }
        all.extend(eps);
    }
    // Episodes by task, then in order (rounds ran in order, so a stable sort keeps it).
    all.sort_by_key(|e| e.task_index);
    Ok((all, picks))
}
