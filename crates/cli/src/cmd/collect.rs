//! `promptdt collect`: a family's datasets and prompt sets. Scripted families and task suites
//! (from a Python policy, in the suite's environment) here; the MuJoCo families, whose data come
//! from an RL agent, in `collect_rl`.

use crate::args::CollectArgs;
use crate::cmd::{bar, collect_rl, follow};
use anyhow::{bail, Result};
use pdt_data::mode::Mode;
use pdt_envs::collect_policy::{PolicyCollectConfig, PolicySide};
use pdt_envs::collect_scripted::{CollectConfig, ScriptedFamily};
use pdt_envs::suite::SuiteFamily;
use pdt_envs::EnvFamily;
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
    if let Some(suite) = family.as_suite() {
        return collect_suite(a, suite);
    }
    if a.policy.is_some() {
        bail!(
            "--policy is for task suites (a suite.toml, docs/your-own-tasks.md); {} collects \
               with its own policies",
            family.name()
        );
    }
    if family.scripted().is_none() && family.rl_preset().is_none() {
        bail!(
            "{} has neither scripted policies nor an RL agent preset to collect with",
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

/// A task suite's datasets from a Python policy (`--policy module:callable`), played in the
/// suite's `[environment]` by the worker (`pdt_envs::collect_policy`).
fn collect_suite(a: &CollectArgs, suite: &SuiteFamily) -> Result<()> {
    let Some(policy) = &a.policy else {
        bail!(
            "{} is a task suite: collecting its data needs a policy, --policy module:callable \
             (docs/your-own-tasks.md); or write its datasets with `promptdt data import` or \
             Python's promptdt.write_dataset",
            suite.path().display()
        );
    };
    let rl_only = [
        ("--from-pretrained", a.from_pretrained),
        ("--resume", a.resume),
        ("--deterministic", a.deterministic),
        ("--explore", a.explore),
        ("--run-dir", a.run_dir.is_some()),
        ("--algorithm", a.algorithm.is_some()),
        ("--steps", a.steps.is_some()),
    ];
    if let Some((flag, _)) = rl_only.iter().find(|(_, given)| *given) {
        bail!("{flag} is for the families collected by an RL agent, not for a task suite");
    }
    let mut cfg = PolicyCollectConfig::new(suite, policy.clone());
    cfg.seed = a.seed;
    cfg.medium = a.medium_policy.clone();
    cfg.prompt_rule = format!("best:{}", a.prompt_episodes).parse().map_err(anyhow::Error::msg)?;
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
        cfg.action_noise = s;
    }
    if let Some(s) = a.medium_noise {
        cfg.medium_noise = s;
    }
    if let Some(n) = a.envs_per_task {
        cfg.envs_per_task = n;
    }
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from("data").join(suite.name()));
    let pb = bar(0, "collect {bar:30} {pos}/{len} episodes [{elapsed} < {eta}]");
    let summary =
        pdt_envs::collect_policy::collect(suite, &cfg, PolicySide::Worker, &out, &mut follow(&pb))?;
    pb.finish_and_clear();
    out!("{summary} to {}", out.display());
    Ok(())
}
