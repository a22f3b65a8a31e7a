//! What a run's evaluation feeds as return tokens, shared by the trainer's evaluations and an
//! acting policy, so that a policy acting on a plan takes the evaluation's actions. (The plans
//! themselves, what an evaluation draws per task, are test time's: `pdt_eval::testtime::plan`.)

use pdt_eval::EvalReturns;
use pdt_rundir::config::{MtBcEval, TrainConfig};

/// The return tokens a run's evaluation feeds (Prompt-MT-BC and MT-BC-Finetune: constant or zero).
pub fn eval_returns(cfg: &TrainConfig) -> EvalReturns {
    match (cfg.run.method.zeroes_history_returns(), cfg.eval.mt_bc_returns) {
        (false, _) => EvalReturns::Decreasing,
        (true, MtBcEval::Reference) => EvalReturns::Constant,
        (true, MtBcEval::Paper) => EvalReturns::Zero,
    }
}
