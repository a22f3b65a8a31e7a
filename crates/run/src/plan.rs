//! What an evaluation of a run draws and feeds, shared by the trainer's evaluations and an acting
//! policy's evaluation plans, so that a policy acting on a plan takes the evaluation's actions.

use pdt_data::MultiTaskDataset;
use pdt_eval::EvalReturns;
use pdt_prompt::{BatchSampler, Rng, SegmentBatch};
use pdt_rundir::config::{Method, MtBcEval, TrainConfig};
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

/// The return tokens a run's evaluation feeds (Prompt-MT-BC and MT-BC-Finetune: constant or zero).
pub fn eval_returns(cfg: &TrainConfig) -> EvalReturns {
    match (cfg.run.method.zeroes_history_returns(), cfg.eval.mt_bc_returns) {
        (false, _) => EvalReturns::Decreasing,
        (true, MtBcEval::Reference) => EvalReturns::Constant,
        (true, MtBcEval::Paper) => EvalReturns::Zero,
    }
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
