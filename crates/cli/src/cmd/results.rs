//! `promptdt results add | render`: the results registry.

use crate::results_args::{ResultsAddArgs, ResultsRenderArgs};
use anyhow::Result;

/// Archives finished runs, one line per run.
pub fn add(a: &ResultsAddArgs) -> Result<()> {
    for r in pdt_repro::registry::add(&a.to_options())? {
        out!("{r}");
    }
    Ok(())
}

/// RESULTS.md and the README's block from the registry.
pub fn render(a: &ResultsRenderArgs) -> Result<()> {
    for f in pdt_repro::render::write(&a.to_options())? {
        out!("wrote {}", f.display());
    }
    Ok(())
}
