//! `promptdt model forward`: a checkpoint run on stored inputs, the actions written to a file.

use crate::args::ForwardArgs;
use anyhow::{bail, Result};

pub fn forward(a: &ForwardArgs) -> Result<()> {
    match a.threads {
        Some(0) => bail!("--threads must be at least 1"),
        Some(t) => tch::set_num_threads(i32::try_from(t).unwrap_or(i32::MAX)),
        None => {}
    }
    let device = pdt_torch::device::resolve(a.device)?;
    let run = pdt_run::files::run_architecture_of(&a.weights)?;
    let s = pdt_model::forward_file::forward_file(
        &a.weights,
        &a.inputs,
        &a.out,
        device,
        a.n_head,
        run.as_ref(),
    )?;
    // Formatted here, not by pdt-model: its summary does not know the file it was written to.
    out!(
        "wrote action_preds [{}, {}, {}] to {} (prompt: {} steps)",
        s.batch,
        s.history_steps,
        s.act_dim,
        a.out.display(),
        s.prompt_steps
    );
    Ok(())
}
