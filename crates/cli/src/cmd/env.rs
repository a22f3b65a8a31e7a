//! `promptdt env replay`: actions applied to a family's task from an initial state, the
//! observations, rewards and flags written to a file.

use crate::args::ReplayArgs;
use anyhow::{Context, Result};
use std::path::Path;

pub fn replay(a: &ReplayArgs) -> Result<()> {
    let read = |p: &Path| {
        pdt_base::fs::read_text_limited(p, pdt_base::fs::MAX_TEXT_BYTES)
            .with_context(|| format!("reading {}", p.display()))
    };
    let actions: Vec<Vec<f32>> = serde_json::from_str(&read(&a.actions)?).with_context(|| {
        format!("{}: expected a JSON array of actions (arrays of numbers)", a.actions.display())
    })?;
    // An unknown family is named as such, before its initial state is read; the family itself
    // knows what initial state it takes (`EnvFamily::replay`).
    let family = pdt_envs::family(&a.env)?;
    let init = a.init.as_deref().map(read).transpose()?;
    let r = family.replay(a.task, init.as_deref(), &actions);
    let r = match &a.init {
        Some(p) => r.with_context(|| format!("--init {}", p.display()))?,
        None => r?,
    };
    let text = serde_json::to_string(&r)?;
    pdt_base::fs::write_atomic(&a.out, text.as_bytes())
        .with_context(|| format!("writing {}", a.out.display()))?;
    out!("{r}, wrote {}", a.out.display());
    Ok(())
}
