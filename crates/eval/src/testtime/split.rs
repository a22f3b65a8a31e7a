//! A split's evaluation under a [`TestTime`]: every task planned as the reference plans it
//! ([`SplitEval::plan_tasks`]), then acted on with the reference rule, a prompt strategy's prompts
//! ([`super::select`]) or each task's `[eval.adapt]` adaptation ([`super::task`]), all tasks'
//! episodes stepped together where the test time allows. The choices and adaptations draw from a
//! generator of their own, seeded from the evaluation's stream after the plans, so a test time
//! never moves the reference's reset seeds.
//!
//! The adaptations of a learner's own weights (MT-BC-Finetune's fine-tuning, MACAW's) are their
//! learners' (`pdt-train`), which own the weights and their optimiser.

use super::plan::{summarise_plans, SplitEval, TaskPlan};
use super::select::{choose_prompt, pick, NearestStart};
use super::task::{adapt_task, check_adaptable, start_prompt, AdaptTask, Adapted};
use super::{AdaptConfig, AdaptKind, AdaptLog, TestTimeError};
use crate::testtime::adapt::PromptScore;
use crate::{EpisodeRecord, EvalError, GivenPrompts};
use crate::{EvalTask, TaskResult};
use pdt_model::PrefixCache;
use pdt_prompt::bandit::SegmentBandit;
use pdt_prompt::{BatchSampler, PromptPick, PromptStrategy, PromptStrategyKind, Rng, SegmentBatch};
use rand::{RngCore, SeedableRng};
use tch::nn::VarStore;
use tch::Tensor;

/// A split's evaluation: per-task results, and what the test time chose and adapted on the way.
#[derive(Debug, Default)]
pub struct SplitResult {
    pub results: Vec<TaskResult>,
    /// The strategy's choices; empty for the reference rule.
    pub picks: Vec<PromptPick>,
    /// Each task's adaptation; empty without one.
    pub adapt_log: Vec<AdaptLog>,
}

/// The reference rule: each task's planned prompt for all its episodes.
pub fn evaluate_reference(ev: &SplitEval<'_>, rng: &mut Rng) -> Result<SplitResult, TestTimeError> {
    let plans = ev.plan_tasks(rng)?;
    let tasks = plans.iter().map(|p| ev.task(p, &p.seeds, p.prompt.clone())).collect();
    let eps = ev.evaluate(ev.model, tasks, None, None)?;
    Ok(SplitResult { results: summarise_plans(&plans, &eps), ..Default::default() })
}

/// A prompt strategy other than the reference rule (`[eval.prompt]`, `promptdt eval
/// --prompt-strategy`; docs/prompt-control.md), all tasks' episodes stepped together (the bandit:
/// one round of `bandit.episodes_per_round` episodes per task at a time).
pub fn evaluate_strategy(
    ev: &SplitEval<'_>,
    strategy: &PromptStrategy,
    rng: &mut Rng,
) -> Result<SplitResult, TestTimeError> {
    if !ev.method.uses_prompt() {
        return Err(TestTimeError::Input(format!(
            "prompt strategy `{}`: {} takes no prompt",
            strategy.strategy,
            ev.method.name()
        )));
    }
    let plans = ev.plan_tasks(rng)?;
    let mut srng = Rng::seed_from_u64(rng.next_u64());
    let sampler = ev.strategy_sampler(strategy)?;
    let stride = strategy.stride_for(sampler.config().prompt_length);
    let (results, picks) = match strategy.strategy {
        PromptStrategyKind::Reference
        | PromptStrategyKind::RandomSegment
        | PromptStrategyKind::BestReturn => {
            // One prompt per task, shared by its episodes (as the reference shares its draw).
            let mut picks = Vec::new();
            let mut tasks = Vec::with_capacity(plans.len());
            for (i, plan) in plans.iter().enumerate() {
                let chosen = choose_prompt(&sampler, i, strategy, &mut srng, None)?;
                if strategy.strategy != PromptStrategyKind::Reference {
                    picks.push(pick(&plan.name, 0, chosen.segments, None));
                }
                tasks.push(ev.task(plan, &plan.seeds, Some(chosen.prompt)));
            }
            let results = summarise_plans(&plans, &ev.evaluate(ev.model, tasks, None, None)?);
            for p in &mut picks {
                if let Some(r) = results.iter().find(|r| r.task == p.task) {
                    p.episode_return = r.return_mean;
                }
            }
            (results, picks)
        }
        PromptStrategyKind::NearestStart => {
            let tasks = plans.iter().map(|p| ev.task(p, &p.seeds, None)).collect();
            let names: Vec<String> = plans.iter().map(|p| p.name.clone()).collect();
            let mut chooser = NearestStart::new(&sampler, stride, &names);
            let eps = ev.evaluate(ev.model, tasks, Some(&mut chooser), None)?;
            let mut picks = chooser.into_picks();
            for (p, k) in picks.iter_mut() {
                let ep = eps.iter().filter(|e| e.task_index == *k).nth(p.episode);
                p.episode_return = ep.map_or(f64::NAN, |e| e.episode_return);
            }
            (summarise_plans(&plans, &eps), picks.into_iter().map(|(p, _)| p).collect())
        }
        PromptStrategyKind::Bandit => {
            let (eps, picks) = bandit_rounds(ev, &sampler, &plans, strategy, stride, &mut srng)?;
            (summarise_plans(&plans, &eps), picks)
        }
    };
    Ok(SplitResult { results, picks, adapt_log: Vec::new() })
}

/// The bandit's rounds: each round, every task's bandit picks its arms, the tasks' round episodes
/// run together, and each bandit learns its episodes' returns. Returns every episode (task
/// positions as in `plans`, episodes in order) and one pick per task and round.
fn bandit_rounds(
    ev: &SplitEval<'_>,
    sampler: &BatchSampler<'_>,
    plans: &[TaskPlan],
    strategy: &PromptStrategy,
    stride: usize,
    rng: &mut Rng,
) -> Result<(Vec<EpisodeRecord>, Vec<PromptPick>), TestTimeError> {
    let j = sampler.config().prompt_episodes;
    let mut bandits = plans
        .iter()
        .enumerate()
        .map(|(i, p)| {
            SegmentBandit::new(strategy.bandit.clone(), sampler.candidate_segments(i, stride), j)
                .ok_or_else(|| {
                    TestTimeError::Input(format!("task {}: no candidate segment", p.name))
                })
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
            tasks.push(ev.task(plan, &plan.seeds[first..last], Some(prompt)));
            picks.push(pick(&plan.name, first, segments, Some((round, c.explored))));
            choices.push(c);
        }
        let eps = ev.evaluate(ev.model, tasks, None, None)?;
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

/// `[eval.adapt]` (`promptdt eval --adapt`; docs/prompt-control.md): per task, the prompt
/// `strategy` picks (one per task: `reference`, `random-segment` or `best-return`) is the
/// starting point; soft prompt tuning, the Prompt-Tuning DT update or LoRA adapt from the task's
/// demonstrations, the backbone frozen, or full fine-tuning tunes every weight (`ev.weights`, put
/// back after the task's episodes); then the task's episodes run with the result.
pub fn evaluate_adapted(
    ev: &SplitEval<'_>,
    strategy: &PromptStrategy,
    cfg: &AdaptConfig,
    rng: &mut Rng,
) -> Result<SplitResult, TestTimeError> {
    check_adaptable(ev.method, strategy, cfg)?;
    let plans = ev.plan_tasks(rng)?;
    let mut arng = Rng::seed_from_u64(rng.next_u64());
    // The probe batches (loss before/after) come from a generator of their own, so they are the
    // same whichever adaptation runs: the logs of two adaptations compare task by task.
    let probe_seed = rng.next_u64();
    let sampler = ev.strategy_sampler(strategy)?;
    let model = ev.model;
    // Full fine-tuning changes the model's own weights: they are put back after each task.
    let weights = match (cfg.kind, ev.weights) {
        (AdaptKind::Full, Some(vs)) => Some(vs),
        (AdaptKind::Full, None) => {
            return Err(TestTimeError::Input(
                "eval.adapt.kind = \"full\": this evaluation has no access to the model's \
                 weights to fine-tune"
                    .into(),
            ))
        }
        _ => None,
    };
    let trainable = weights.map(VarStore::trainable_variables);
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
            weights: trainable.as_deref(),
            probe_seed: probe_seed.wrapping_add(i as u64),
        };
        // Restores the weights when this task is done, its episodes run or an error on the way.
        let _restore = weights.map(Restore::of);
        let mut online = ReturnScore { ev, plan, episodes: cfg.ptdt.score_episodes };
        let a = adapt_task(&task, &start, Some(&mut online), &mut arng)?;
        log.push(a.log.clone());
        match a.adapted {
            Adapted::Tokens(_) => prefixes.push(a.prefix(model)),
            Adapted::Prompt(p) => tuned.push(p),
            Adapted::Lora { .. } => {
                let given = GivenPrompts { prefix: a.prefix(model), lora: a.lora() };
                let one = vec![ev.task(plan, &plan.seeds, None)];
                let mut eps = ev.evaluate(model, one, None, Some(given))?;
                eps.iter_mut().for_each(|e| e.task_index = i);
                all.extend(eps);
            }
            // The tuned weights are this task's alone: its episodes run now, alone, with the
            // start prompt as an ordinary prompt (as the reference rule's and PTDT's run).
            Adapted::Full(p) => {
                let one = vec![ev.task(plan, &plan.seeds, Some(p))];
                let mut eps = ev.evaluate(model, one, None, None)?;
                eps.iter_mut().for_each(|e| e.task_index = i);
                all.extend(eps);
            }
        }
    }
    match cfg.kind {
        AdaptKind::SoftPrompt => {
            let refs: Vec<&PrefixCache> = prefixes.iter().collect();
            let prefix = PrefixCache::cat(&refs).ok_or_else(|| {
                TestTimeError::Failed("tuned prompts of different lengths".into())
            })?;
            let tasks = plans.iter().map(|p| ev.task(p, &p.seeds, None)).collect();
            all = ev.evaluate(model, tasks, None, Some(GivenPrompts { prefix, lora: None }))?;
        }
        AdaptKind::Ptdt => {
            let tasks = plans
                .iter()
                .zip(tuned)
                .map(|(p, t)| ev.task(p, &p.seeds, Some(t)))
                .collect::<Vec<EvalTask>>();
            all = ev.evaluate(model, tasks, None, None)?;
        }
        AdaptKind::Lora | AdaptKind::Full | AdaptKind::None => {}
    }
    Ok(SplitResult { results: summarise_plans(&plans, &all), picks: Vec::new(), adapt_log: log })
}

/// A copy of every variable of a model, written back into it when dropped: full fine-tuning's
/// weights are the run's own, and each task starts from them as saved (bit for bit), whatever
/// happened to the task before (an error included).
struct Restore<'a> {
    vs: &'a VarStore,
    saved: Vec<(String, Tensor)>,
}

impl<'a> Restore<'a> {
    fn of(vs: &'a VarStore) -> Self {
        let saved =
            tch::no_grad(|| vs.variables().into_iter().map(|(n, t)| (n, t.copy())).collect());
        Self { vs, saved }
    }
}

impl Drop for Restore<'_> {
    fn drop(&mut self) {
        tch::no_grad(|| {
            let vars = self.vs.variables();
            for (n, saved) in &self.saved {
                if let Some(v) = vars.get(n) {
                    v.shallow_clone().copy_(saved);
                }
            }
        });
    }
}

/// The online score: the mean return of `episodes` episodes per candidate in the task's
/// environment, every candidate on the same reset seeds (drawn per call, apart from the
/// evaluation's), all candidates' episodes stepped together.
struct ReturnScore<'a> {
    ev: &'a SplitEval<'a>,
    plan: &'a TaskPlan,
    episodes: usize,
}

impl PromptScore for ReturnScore<'_> {
    fn scores(
        &mut self,
        candidates: &[SegmentBatch],
        rng: &mut Rng,
    ) -> Result<Vec<f64>, EvalError> {
        let seeds: Vec<u64> = (0..self.episodes).map(|_| rng.next_u64()).collect();
        let tasks =
            candidates.iter().map(|c| self.ev.task(self.plan, &seeds, Some(c.clone()))).collect();
        let eps = self.ev.evaluate(self.ev.model, tasks, None, None)?;
        Ok((0..candidates.len())
            .map(|k| {
                let r: Vec<f64> =
                    eps.iter().filter(|e| e.task_index == k).map(|e| e.episode_return).collect();
                r.iter().sum::<f64>() / r.len().max(1) as f64
            })
            .collect())
    }
}
