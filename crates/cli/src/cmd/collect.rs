//! `promptdt collect`: a family's datasets and prompt sets. Scripted families here; the MuJoCo
//! families, whose data come from an RL agent, in `collect_rl`.

use crate::args::CollectArgs;
use crate::cmd::{bar, collect_rl, follow};
use anyhow::{bail, Result};
use pdt_data::mode::Mode;
use pdt_envs::collect_scripted::{CollectConfig, ScriptedFamily};
use std::path::PathBuf;

/// The scripted families `keep` holds for, by name: messages name them from pdt-envs, so a new
/// family needs no edit here.
fn families_where(keep: fn(ScriptedFamily) -> bool) -> String {
    let names: Vec<_> =
        ScriptedFamily::all().into_iter().filter(|f| keep(*f)).map(|f| f.name()).collect();
    names.join(", ")
}

pub fn collect(a: &CollectArgs) -> Result<()> {
    let family = pdt_envs::family(&a.env)?;
    if family.scripted().is_none() && family.rl_preset().is_none() {
        // A task suite's data come from its user (docs/your-own-tasks.md), not from promptdt.
        bail!(
            "{} has neither scripted policies nor an RL agent preset to collect with: write its \
             datasets with `promptdt data import` or Python's promptdt.write_dataset \
             (docs/your-own-tasks.md)",
            family.name()
        );
    }
    let Some(scripted) = family.scripted() else {
        if a.modes.is_some() {
            bail!("--modes is for the scripted families ({})", families_where(|_| true));
        }
        if a.action_noise.is_some() {
            bail!("--action-noise is for {}", families_where(ScriptedFamily::takes_action_noise));
        }
        return collect_rl::collect(a, family.name());
    };
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from("data").join(family.name()));
    let cfg = config(a, scripted)?;
    let pb = bar(0, "collect {bar:30} {pos}/{len} datasets [{elapsed} < {eta}]");
    let summary = pdt_envs::collect_scripted::collect(&cfg, &out, &mut follow(&pb))?;
    pb.finish_and_clear();
    out!("{summary} to {}", out.display());
    Ok(())
}

/// The collection the flags ask for: the family's defaults with what was given.
fn config(a: &CollectArgs, scripted: ScriptedFamily) -> Result<CollectConfig> {
    let mut cfg = CollectConfig::for_family(scripted);
    cfg.seed = a.seed;
    cfg.prompt_episodes = a.prompt_episodes;
    if let Some(n) = a.episodes {
        cfg.episodes_per_task = n;
    }
    if let Some(t) = &a.tasks {
        cfg.tasks = t.clone();
    }
    if let Some(m) = &a.modes {
        cfg.modes = m.iter().map(|m| m.parse::<Mode>()).collect::<Result<_, _>>()?;
    }
    if let Some(s) = a.action_noise {
        if !scripted.takes_action_noise() {
            bail!("--action-noise is for {}", families_where(ScriptedFamily::takes_action_noise));
        }
        cfg.reach_action_noise = s;
    }
    Ok(cfg)
}
