//! `promptdt eval`: a run's latest checkpoint on its held-out tasks (or `--split train`), with the
//! prompt strategy and adaptation the flags ask for (`crate::eval_flags`).

use crate::args::EvalArgs;
use crate::eval_flags;
use anyhow::Result;

pub fn eval(a: &EvalArgs) -> Result<()> {
    let req = request(a)?;
    let prompted = pdt_train::run::evaluate_run_as(&a.run, &req)?;
    out!("{prompted}; wrote {}/{}", a.run.display(), prompted.file_name());
    Ok(())
}

/// The evaluation the flags ask for, checked.
fn request(a: &EvalArgs) -> Result<pdt_train::run::EvalRequest> {
    eval_flags::check_eval_flags(a).map_err(anyhow::Error::msg)?;
    // --adapt-steps / --adapt-batch are the budget of the adaptation --adapt names: an
    // [eval.adapt] kind's, or the run's own (MACAW's, MT-BC-Finetune's).
    let (adapt, macaw) = match (a.adaptation.adapt, a.adapt_steps.or(a.adapt_batch)) {
        (None, None) => (None, Default::default()),
        _ => {
            let run = pdt_rundir::RunDir::at(&a.run);
            let cfg = pdt_policy::files::run_config(&run, None, a.data.as_deref())?;
            let test_time = pdt_rundir::config::TestTime::of(&cfg);
            let own = eval_flags::own_budget(a, &test_time, cfg.run.method)
                .map_err(anyhow::Error::msg)?;
            (eval_flags::eval_adapt(a, &cfg.eval.adapt), own.unwrap_or_default())
        }
    };
    Ok(pdt_train::run::EvalRequest {
        episodes: a.episodes,
        split: a.split.clone(),
        device: a.device,
        data: a.data.clone(),
        macaw,
        prompt: eval_flags::eval_prompt(a),
        adapt,
    })
}
