//! `promptdt eval`: a run's latest checkpoint on its held-out tasks (or `--split train`), with the
//! prompt strategy and adaptation the flags ask for (`crate::eval_flags`).

use crate::args::EvalArgs;
use crate::eval_flags;
use anyhow::Result;

pub fn eval(a: &EvalArgs) -> Result<()> {
    let req = request(a)?;
    // A run with no environment (a suite without `[environment]`) is evaluated on its tasks'
    // data: an action error, printed and written as such, never as a return.
    if pdt_train::run::evaluates_offline(&a.run)? {
        let e = pdt_train::run::evaluate_run_offline(&a.run, &req)?;
        out!("{e}; wrote {}", pdt_rundir::RunDir::at(&a.run).offline_final_path().display());
        return Ok(());
    }
    let prompted = pdt_train::run::evaluate_run_as(&a.run, &req)?;
    out!("{prompted}; wrote {}/{}", a.run.display(), prompted.file_name());
    if let Some(rep) = &prompted.eval.repeats {
        out!(
            "{} repeats (the rows above: repeat 0): average {:.2} ± {:.2} (sample std over \
             repeats: evaluation noise)",
            rep.mean_returns.len(),
            rep.mean_returns.iter().sum::<f64>() / rep.mean_returns.len() as f64,
            rep.mean_return_sd
        );
    }
    Ok(())
}

/// The evaluation the flags ask for, checked.
fn request(a: &EvalArgs) -> Result<pdt_train::run::EvalRequest> {
    eval_flags::check_eval_flags(a).map_err(anyhow::Error::msg)?;
    Ok(pdt_train::run::EvalRequest {
        episodes: a.episodes,
        split: a.split.clone(),
        device: a.device,
        data: a.data.clone(),
        test_time: eval_flags::eval_test_time(a)?,
        repeats: a.repeats,
    })
}
