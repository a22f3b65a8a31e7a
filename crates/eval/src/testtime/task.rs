//! One test task adapted from its demonstrations (`[eval.adapt]`,
//! docs/prompt-control.md): what an adaptation does with a task, for every caller: `promptdt
//! eval --adapt` (pdt-train's adapted evaluation), `promptdt serve` (episodes opened with `adapt`)
//! and the Python `Policy.adapt` (both through `pdt_policy::Policy::adapt`). The algorithms are
//! [`super::adapt`]'s; this picks the start prompt and the demonstrations, measures the probe loss
//! before and after, and keeps what the task's episodes then act with ([`TaskAdaptation`]).

use super::adapt::{self, demo_loss, ActionLossScore, PromptScore};
use super::{AdaptConfig, AdaptKind, AdaptLog, PtdtScore, TestTimeError};
use crate::to_segments;
use pdt_model::{LoraAdapters, PrefixCache, PromptDt, PromptTokens};
use pdt_prompt::{BatchSampler, PromptStrategy, PromptStrategyKind, Rng, SegmentBatch};
use pdt_rundir::config::Method;
use rand::SeedableRng;
use std::time::Instant;
use tch::Tensor;

/// What an adaptation made of a task's prompt.
#[derive(Debug)]
pub enum Adapted {
    /// Soft prompt tuning: the tuned embedded prompt tokens (`[1, 3Lp, H]`).
    Tokens(PromptTokens),
    /// Prompt-Tuning DT: the tuned prompt's inputs.
    Prompt(SegmentBatch),
    /// LoRA: the start prompt's tokens, acted on through the task's adapters.
    Lora { prompt: PromptTokens, adapters: LoraAdapters },
    /// Full fine-tuning: the start prompt, acted on with the model's weights as tuned (in place,
    /// until the caller restores them).
    Full(SegmentBatch),
}

/// One task's adaptation: what its episodes act with, and its log (probe loss before and after,
/// values adapted, seconds).
#[derive(Debug)]
pub struct TaskAdaptation {
    pub adapted: Adapted,
    pub log: AdaptLog,
}

impl TaskAdaptation {
    /// The prompt's keys and values (one row) the task's episodes act with.
    pub fn prefix(&self, model: &PromptDt) -> PrefixCache {
        tch::no_grad(|| match &self.adapted {
            Adapted::Tokens(t) => model.prefix(t, None),
            Adapted::Prompt(p) | Adapted::Full(p) => {
                model.prefix(&to_segments(p, model.device()), None)
            }
            Adapted::Lora { prompt, adapters } => model.prefix(prompt, Some(adapters)),
        })
    }

    /// LoRA's adapters (every forward of the task's episodes goes through them); `None` otherwise.
    pub fn lora(&self) -> Option<&LoraAdapters> {
        match &self.adapted {
            Adapted::Lora { adapters, .. } => Some(adapters),
            _ => None,
        }
    }
}

/// One task to adapt: the model, the sampler over the task's demonstrations and its settings.
pub struct AdaptTask<'a> {
    pub model: &'a PromptDt,
    pub sampler: &'a BatchSampler<'a>,
    /// The task's index among `sampler`'s tasks.
    pub index: usize,
    /// `cheetah_vel-2`, for the log and errors.
    pub name: &'a str,
    pub cfg: &'a AdaptConfig,
    /// The model's trainable variables, which full fine-tuning changes in place (its caller keeps
    /// a copy and restores them after the task's episodes); `None` where the weights must not
    /// change (a served or Python policy, whose episodes of several tasks share them), and then
    /// `full` is refused.
    pub weights: Option<&'a [Tensor]>,
    /// Seeds the probe batch (the loss before and after), drawn apart from the adaptation's
    /// stream so that two adaptations' logs compare task by task.
    pub probe_seed: u64,
}

/// Adapts to `task` from `start` (the prompt the strategy picked), drawing from `rng`.
/// `return_score` ranks PTDT's candidates when `ptdt.score = "return"` (it steps the task's
/// environment: only the evaluation has one); the action-loss score needs none.
pub fn adapt_task(
    task: &AdaptTask<'_>,
    start: &SegmentBatch,
    return_score: Option<&mut dyn PromptScore>,
    rng: &mut Rng,
) -> Result<TaskAdaptation, TestTimeError> {
    let AdaptTask { model, sampler, index, name, cfg, weights, probe_seed } = *task;
    let device = model.device();
    let prompt = to_segments(start, device);
    let mut demos =
        |n: usize, r: &mut Rng| to_segments(&sampler.demo_segments(index, n, r), device);
    let probe = demos(cfg.batch, &mut Rng::seed_from_u64(probe_seed));
    let loss_of = |p: &PromptTokens, lora| {
        tch::no_grad(|| demo_loss(model, &probe, p, lora).double_value(&[]))
    };
    let start_tokens = tch::no_grad(|| model.prompt_tokens(&prompt));
    let loss_before = loss_of(&start_tokens, None);
    let clock = Instant::now();
    let fail = |e: super::AdaptError| TestTimeError::Failed(format!("task {name}: {e}"));
    let (adapted, trainable) = match cfg.kind {
        AdaptKind::SoftPrompt => {
            let t = adapt::soft_prompt(model, &prompt, cfg, &mut demos, rng).map_err(fail)?;
            let n = t.tokens.numel();
            (Adapted::Tokens(t), n)
        }
        AdaptKind::Ptdt => {
            let tuned = match (cfg.ptdt.score, return_score) {
                (PtdtScore::ActionLoss, _) => {
                    let mut score = ActionLossScore { model, batch: cfg.batch, demos: &mut demos };
                    adapt::ptdt(start, cfg, &mut score, rng)?
                }
                (PtdtScore::Return, Some(score)) => adapt::ptdt(start, cfg, score, rng)?,
                (PtdtScore::Return, None) => {
                    return Err(TestTimeError::Input(format!(
                        "task {name}: eval.adapt.ptdt.score = \"return\" ranks prompts by \
                         episodes in the task's environment, which only `promptdt eval` steps; \
                         use score = \"action-loss\" here"
                    )))
                }
            };
            (Adapted::Prompt(tuned), adapt::ptdt_trainable(start))
        }
        AdaptKind::Lora => {
            let a = adapt::lora(model, &prompt, cfg, &mut demos, rng).map_err(fail)?;
            let n = a.numel();
            (Adapted::Lora { prompt: start_tokens, adapters: a }, n)
        }
        AdaptKind::Full => {
            let Some(weights) = weights else {
                return Err(TestTimeError::Input(format!(
                    "task {name}: eval.adapt.kind = \"full\" fine-tunes the model's weights for \
                     the task's episodes, which only `promptdt eval` does (it restores them after \
                     each task); a policy acts with the weights as saved"
                )));
            };
            adapt::full(model, weights, &prompt, cfg, &mut demos, rng).map_err(fail)?;
            (Adapted::Full(start.clone()), weights.iter().map(Tensor::numel).sum())
        }
        AdaptKind::None => {
            return Err(TestTimeError::Input("no adaptation asked for (eval.adapt.kind)".into()))
        }
    };
    let seconds = clock.elapsed().as_secs_f64();
    let loss_after = match &adapted {
        Adapted::Tokens(t) => loss_of(t, None),
        Adapted::Prompt(p) => {
            let tokens = tch::no_grad(|| model.prompt_tokens(&to_segments(p, device)));
            loss_of(&tokens, None)
        }
        Adapted::Lora { prompt, adapters } => loss_of(prompt, Some(adapters)),
        // The start prompt through the tuned weights.
        Adapted::Full(_) => loss_of(&tch::no_grad(|| model.prompt_tokens(&prompt)), None),
    };
    let log = AdaptLog {
        task: name.to_string(),
        loss_before,
        loss_after,
        steps: cfg.steps,
        trainable,
        seconds,
    };
    Ok(TaskAdaptation { adapted, log })
}

/// The prompt an adaptation starts from: one per task, by a strategy that picks one per task
/// (`reference`, `random-segment`, `best-return`; [`check_adaptable`] refuses the others). `reference` with the run's own prompt
/// settings is the caller's evaluation draw (`default_draw`).
pub fn start_prompt(
    sampler: &BatchSampler<'_>,
    index: usize,
    strategy: &PromptStrategy,
    default_draw: Option<SegmentBatch>,
    rng: &mut Rng,
) -> Result<SegmentBatch, TestTimeError> {
    Ok(match strategy.strategy {
        PromptStrategyKind::Reference if strategy.is_default() => match default_draw {
            Some(p) => p,
            None => sampler.eval_prompt(index, rng),
        },
        PromptStrategyKind::Reference => sampler.eval_prompt(index, rng),
        PromptStrategyKind::RandomSegment => {
            let c = sampler.random_segments(index, rng);
            sampler.prompt_from_choices(index, &c)?
        }
        _ => sampler.prompt_from_choices(index, &sampler.best_return_segments(index))?,
    })
}

/// Refuses what cannot be adapted, naming it: a method without a prompt, a strategy that picks
/// a prompt per episode or learns across episodes (an adaptation starts from one prompt per
/// task), settings out of range.
pub fn check_adaptable(
    method: Method,
    strategy: &PromptStrategy,
    cfg: &AdaptConfig,
) -> Result<(), TestTimeError> {
    if !method.uses_prompt() {
        return Err(TestTimeError::Input(format!(
            "adaptation `{}`: {} takes no prompt; the adaptations apply to {} runs",
            cfg.kind,
            method.name(),
            Method::names_where(Method::uses_prompt)
        )));
    }
    if strategy.strategy.per_episode() || strategy.strategy.learns_from_returns() {
        return Err(TestTimeError::Input(format!(
            "an adaptation starts from one prompt per task; prompt strategy `{}` picks one per \
             episode or round (use reference, random-segment or best-return)",
            strategy.strategy
        )));
    }
    cfg.validate().map_err(|e| TestTimeError::Input(e.to_string()))
}
