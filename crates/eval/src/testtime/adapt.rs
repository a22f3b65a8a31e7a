//! The algorithms of the `[eval.adapt]` adaptations to a test task from its few demonstrations
//! (`docs/prompt-control.md`): soft prompt tuning, the Prompt-Tuning DT update and LoRA adapters,
//! the backbone frozen, and full fine-tuning of every weight, their matched baseline.
//! `[eval.adapt]` ([`AdaptConfig`]) says which and its budget.
//!
//! Every adaptation learns from the action loss (the reference's masked MSE) on K-step segments
//! of the task's demonstrations (`BatchSampler::demo_segments`), with the model in eval mode (no
//! dropout: the only randomness is the caller's generator). Gradients are taken with respect to
//! the adapted tensors only (`Tensor::run_backward` on them, stepped by [`super::optim::Adam`]),
//! so the model's weights neither change nor accumulate gradients, except in [`full`], whose
//! adapted tensors are the weights (changed in place; the caller restores them).

use super::optim::Adam;
use crate::EvalError;
use pdt_model::prompt_dt::{Prompt, Sequence};
use pdt_model::{LastBlock, LoraAdapters, LoraShape, PromptDt, PromptTokens, Segments};
use pdt_prompt::{Rng, SegmentBatch};
use pdt_rundir::config::{AdaptConfig, AdaptError, LoraConfig};
use rand::Rng as _;
use tch::{Kind, Tensor};

/// Demonstration segments of one task, drawn on demand from the caller's sampler and stream.
pub type DemoSource<'a> = dyn FnMut(usize, &mut Rng) -> Segments + 'a;

/// The masked action loss of `model` on the history segments `demos` (`[B, K]`) after the
/// embedded prompt `prompt` (`[1, 3Lp, H]`, repeated for every row), with optional adapters.
pub fn demo_loss(
    model: &PromptDt,
    demos: &Segments,
    prompt: &PromptTokens,
    lora: Option<&LoraAdapters>,
) -> Tensor {
    let b = demos.batch_size();
    let k = demos.len();
    let p = PromptTokens {
        tokens: prompt.tokens.expand([b, -1, -1], false), // [B, 3Lp, H]
        mask: prompt.mask.expand([b, -1], false),         // [B, 3Lp]
    };
    // Every token through the last block (the reference's ops), whatever the model's own setting:
    // the adaptation's loss has always been computed so.
    let all = model.forward(
        demos,
        Sequence {
            prompt: Some(Prompt::Tokens(&p)),
            lora,
            last_block: Some(LastBlock::AllTokens),
            ..Sequence::eval(None)
        }
        .all_steps(),
    ); // [B, Lp+K, da]
    let steps = all.size()[1];
    let preds = all.narrow(1, steps - k, k); // [B, K, da]
    PromptDt::action_loss(&preds, &demos.actions, &demos.mask)
}

fn scalar(t: &Tensor) -> f64 {
    t.to_kind(Kind::Double).double_value(&[])
}

/// `cfg.steps` Adam steps of the demonstrations' action loss on `params`; `loss` builds the loss
/// of one demonstration batch. A non-finite loss stops it with an error naming the rate.
fn gradient_steps(
    params: &[&Tensor],
    cfg: &AdaptConfig,
    demos: &mut DemoSource<'_>,
    rng: &mut Rng,
    loss: &dyn Fn(&Segments) -> Tensor,
) -> Result<(), AdaptError> {
    let mut adam = Adam::new(params, cfg.lr);
    for step in 0..cfg.steps {
        let batch = demos(cfg.batch, rng);
        let l = loss(&batch);
        let grads = Tensor::f_run_backward(&[&l], params, false, false)
            .map_err(|e| AdaptError(format!("adaptation step {step}: backward failed: {e}")))?;
        if !scalar(&l).is_finite() {
            return Err(AdaptError(format!(
                "adaptation step {step}: the demonstrations' action loss is not finite; lower \
                 eval.adapt.lr = {}",
                cfg.lr
            )));
        }
        adam.step(params, &grads);
    }
    Ok(())
}

/// (a) Soft prompt tuning: the embedded prompt tokens (initialised from `prompt`, the prompt
/// the strategy picked, `[1, J*H]`) learned by `cfg.steps` Adam steps of the action loss on the
/// task's demonstration segments, the model frozen. Returns the tuned tokens (`[1, 3Lp, H]`).
pub fn soft_prompt(
    model: &PromptDt,
    prompt: &Segments,
    cfg: &AdaptConfig,
    demos: &mut DemoSource<'_>,
    rng: &mut Rng,
) -> Result<PromptTokens, AdaptError> {
    let init = tch::no_grad(|| model.prompt_tokens(prompt));
    let tokens = init.tokens.detach().copy().set_requires_grad(true);
    let mask = init.mask.detach();
    let loss = |b: &Segments| {
        let p = PromptTokens { tokens: tokens.shallow_clone(), mask: mask.shallow_clone() };
        demo_loss(model, b, &p, None)
    };
    gradient_steps(&[&tokens], cfg, demos, rng, &loss)?;
    Ok(PromptTokens { tokens: tokens.detach(), mask })
}

/// (c) LoRA: a fresh adapter set (A ~ N(0, `init_std`) from `rng`, B zero: step 0 is the frozen
/// model) trained by `cfg.steps` Adam steps of the action loss on the task's demonstration
/// segments after the prompt `prompt` (`[1, J*H]`), the backbone frozen.
pub fn lora(
    model: &PromptDt,
    prompt: &Segments,
    cfg: &AdaptConfig,
    demos: &mut DemoSource<'_>,
    rng: &mut Rng,
) -> Result<LoraAdapters, AdaptError> {
    let adapters = new_adapters(model, &cfg.lora, rng);
    let tokens = tch::no_grad(|| model.prompt_tokens(prompt));
    let params = adapters.parameters();
    let loss = |b: &Segments| demo_loss(model, b, &tokens, Some(&adapters));
    gradient_steps(&params, cfg, demos, rng, &loss)?;
    Ok(adapters)
}

/// (d) Full fine-tuning: every weight of the model (`weights`: its trainable variables, changed
/// in place, so the caller keeps a copy and restores it) by `cfg.steps` Adam steps of the action
/// loss on the task's demonstration segments after the prompt `prompt` (`[1, J*H]`, embedded anew
/// at every step, so the prompt embeddings learn too): the data, optimiser, learning rate, steps
/// and batch of soft prompt tuning and LoRA, on all the weights (Prompt-Tuning DT's
/// full-fine-tuning baseline). With 0 steps the weights are untouched.
pub fn full(
    model: &PromptDt,
    weights: &[Tensor],
    prompt: &Segments,
    cfg: &AdaptConfig,
    demos: &mut DemoSource<'_>,
    rng: &mut Rng,
) -> Result<(), AdaptError> {
    // `run_backward` can only differentiate with respect to tensors that track gradients.
    if let Some(i) = weights.iter().position(|w| !w.requires_grad()) {
        return Err(AdaptError(format!(
            "full fine-tuning: weight {i} of {} does not require gradients (a frozen model)",
            weights.len()
        )));
    }
    let params: Vec<&Tensor> = weights.iter().collect();
    let loss = |b: &Segments| demo_loss(model, b, &model.prompt_tokens(prompt), None);
    gradient_steps(&params, cfg, demos, rng, &loss)
}

/// An adapter set for `model` with A's values drawn from `rng`.
pub fn new_adapters(model: &PromptDt, cfg: &LoraConfig, rng: &mut Rng) -> LoraAdapters {
    let shape = LoraShape { rank: cfg.rank, alpha: cfg.alpha, c_proj: cfg.c_proj };
    let std = cfg.init_std as f32;
    let device = model.device();
    LoraAdapters::new(
        &model.cfg,
        shape,
        |n| {
            pdt_base::random::standard_normals_f32(|| rng.random::<f64>(), n)
                .into_iter()
                .map(|x| x * std)
                .collect()
        },
        device,
    )
}

/// Scores prompt candidates for the Prompt-Tuning DT update; higher is better.
pub trait PromptScore {
    fn scores(&mut self, candidates: &[SegmentBatch], rng: &mut Rng)
        -> Result<Vec<f64>, EvalError>;
}

/// The offline score: minus the action loss on one batch of demonstration segments, drawn per
/// call, so every candidate of an iteration meets the same batch.
pub struct ActionLossScore<'a, 'd> {
    pub model: &'a PromptDt,
    pub batch: usize,
    pub demos: &'a mut DemoSource<'d>,
}

impl PromptScore for ActionLossScore<'_, '_> {
    fn scores(
        &mut self,
        candidates: &[SegmentBatch],
        rng: &mut Rng,
    ) -> Result<Vec<f64>, EvalError> {
        let batch = (self.demos)(self.batch, rng);
        let device = self.model.device();
        Ok(candidates
            .iter()
            .map(|c| {
                let p = crate::prompt_batch(&[c], device);
                tch::no_grad(|| {
                    let tokens = self.model.prompt_tokens(&p);
                    -scalar(&demo_loss(self.model, &batch, &tokens, None))
                })
            })
            .collect())
    }
}

/// The positions of a prompt's adapted inputs: the states, actions and returns-to-go of its real
/// (unpadded) steps. Timesteps and the mask are not perturbed.
fn perturbable(p: &SegmentBatch) -> Vec<(Field, usize)> {
    let (ds, da) = (p.state_dim, p.act_dim);
    let mut out = Vec::new();
    for t in 0..p.batch * p.steps {
        if p.mask[t] > 0.0 {
            out.extend((0..ds).map(|j| (Field::State, t * ds + j)));
            out.extend((0..da).map(|j| (Field::Action, t * da + j)));
            out.push((Field::Return, t));
        }
    }
    out
}

#[derive(Debug, Clone, Copy)]
enum Field {
    State,
    Action,
    Return,
}

fn shifted(p: &SegmentBatch, at: &[(Field, usize)], delta: &[f32]) -> SegmentBatch {
    let mut out = p.clone();
    for (&(f, i), &d) in at.iter().zip(delta) {
        match f {
            Field::State => out.states[i] += d,
            Field::Action => out.actions[i] += d,
            Field::Return => out.returns_to_go[i] += d,
        }
    }
    out
}

/// The ranking-based zeroth-order direction (ZO-RankSGD, as Prompt-Tuning DT uses it): with the
/// candidates' perturbations `u` and their scores (higher better), the mean over every ordered
/// pair (better i, worse j) of `u_i - u_j`. Ties add nothing. Only the ranking matters, not the
/// scores' scale.
pub fn rank_direction(perturbations: &[Vec<f32>], scores: &[f64]) -> Vec<f32> {
    let n = perturbations.first().map_or(0, Vec::len);
    let mut g = vec![0f32; n];
    let mut pairs = 0usize;
    for i in 0..scores.len() {
        for j in (i + 1)..scores.len() {
            pairs += 1;
            let sign = match scores[i].partial_cmp(&scores[j]) {
                Some(std::cmp::Ordering::Greater) => 1.0,
                Some(std::cmp::Ordering::Less) => -1.0,
                _ => continue,
            };
            for (k, gk) in g.iter_mut().enumerate() {
                *gk += sign * (perturbations[i][k] - perturbations[j][k]);
            }
        }
    }
    let pairs = pairs.max(1) as f32;
    g.iter_mut().for_each(|x| *x /= pairs);
    g
}

/// (b) The Prompt-Tuning DT update (Hu et al. 2023): per iteration, `ptdt.candidates` Gaussian
/// perturbations (std `ptdt.sigma`) of the prompt's inputs, ranked by `score`, and a step of
/// `ptdt.step` along [`rank_direction`]. Starts from `prompt` (`[1, J*H]`), returns the tuned one.
pub fn ptdt(
    prompt: &SegmentBatch,
    cfg: &AdaptConfig,
    score: &mut dyn PromptScore,
    rng: &mut Rng,
) -> Result<SegmentBatch, EvalError> {
    let at = perturbable(prompt);
    let mut current = prompt.clone();
    let sigma = cfg.ptdt.sigma as f32;
    for _ in 0..cfg.steps {
        let us: Vec<Vec<f32>> = (0..cfg.ptdt.candidates)
            .map(|_| pdt_base::random::standard_normals_f32(|| rng.random::<f64>(), at.len()))
            .collect();
        let candidates: Vec<SegmentBatch> = us
            .iter()
            .map(|u| shifted(&current, &at, &u.iter().map(|x| x * sigma).collect::<Vec<_>>()))
            .collect();
        let scores = score.scores(&candidates, rng)?;
        let g = rank_direction(&us, &scores);
        let step = cfg.ptdt.step as f32;
        current = shifted(&current, &at, &g.iter().map(|x| x * step).collect::<Vec<_>>());
    }
    Ok(current)
}

/// The number of values the Prompt-Tuning DT update adapts in `prompt`.
pub fn ptdt_trainable(prompt: &SegmentBatch) -> usize {
    perturbable(prompt).len()
}
