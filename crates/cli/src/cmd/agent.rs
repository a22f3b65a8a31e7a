//! `promptdt agent combine`: the best snapshot per task of several agents, as one agent.

use crate::args::CombineArgs;
use crate::cmd::{bar, follow};
use anyhow::Result;

pub fn combine(a: &CombineArgs) -> Result<()> {
    let device = pdt_torch::device::resolve(a.device)?;
    let cfg = pdt_rl::combine::CombineConfig {
        base: a.base.clone(),
        candidates: a.snapshots.clone(),
        top_k: a.top_k,
        eval_episodes: a.eval_episodes,
        seed: a.seed,
        mirrors: !a.no_mirrors,
        dataset_noise: a.deterministic_datasets.then_some(pdt_rl::agent::Noise::Deterministic),
    };
    let pb = bar(0, "evaluating {bar:30} {pos}/{len} snapshots [{elapsed} < {eta}]");
    let card = pdt_rl::combine::combine(&cfg, &a.out, device, &mut follow(&pb))?;
    pb.finish_and_clear();
    out!("{}; wrote {}/agent.json", card.experts_table(), a.out.display());
    Ok(())
}
