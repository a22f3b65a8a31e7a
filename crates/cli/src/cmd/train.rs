//! `promptdt train`: one run from a configuration file with the flags' overrides, or a killed run
//! resumed. (A pack, `--pack` or `--resume` of a pack directory, is `cmd::pack`.)

use crate::args::{MacawPresetArg, TrainArgs};
use crate::cmd::bar;
use anyhow::{bail, Result};
use indicatif::ProgressBar;
use pdt_rundir::config::{Overrides, TrainConfig};
use pdt_train::run::{Progress, ResumeWith, TrainOptions};

pub fn train(a: &TrainArgs) -> Result<()> {
    if a.engine.is_some() || a.pack_eval.is_some() {
        bail!("--engine and --pack-eval are for packs (--pack, or --resume of a pack directory)");
    }
    let (cfg, dir) = match (&a.resume, &a.config) {
        (Some(dir), _) => (None, dir.clone()),
        (None, Some(path)) => {
            let cfg = config(a, path)?;
            let dir = a.out.clone().unwrap_or_else(|| cfg.default_run_dir());
            (Some(cfg), dir)
        }
        (None, None) => bail!("give --config or --resume"),
    };
    let pb = if a.quiet {
        ProgressBar::hidden()
    } else {
        bar(0, "train {bar:30} {pos}/{len} it [{elapsed} < {eta}] {msg}")
    };
    let mut last_test: Option<f64> = None;
    let mut progress = |p: &Progress| {
        pb.set_length(p.iterations);
        pb.set_position(p.iteration);
        last_test = p.test_return.or(last_test);
        let test = last_test.map_or(String::new(), |r| format!("  test return {r:.2}"));
        pb.set_message(format!("loss {:.5}{test}", p.loss));
    };
    let resume_with =
        ResumeWith { iterations: a.iterations, device: a.device, data: a.data.clone() };
    let opts = TrainOptions {
        resume: a.resume.is_some(),
        resume_with,
        stop_after_iterations: a.stop_after_iterations,
        progress: &mut progress,
        interrupt: Default::default(),
        envs: None,
    };
    let summary = pdt_train::run::train(cfg, &dir, opts)?;
    pb.finish_and_clear();
    if let Some(mean) = summary.held_out_mean() {
        let done = summary.iterations_done;
        out!("held-out tasks after iteration {done}: average return {mean:.2}");
    }
    if let Some(note) = &summary.note {
        out!("note: {note}");
    }
    out!("run directory: {}", summary.dir.display());
    Ok(())
}

/// The configuration file with the flags' overrides applied.
fn config(a: &TrainArgs, path: &std::path::Path) -> Result<TrainConfig> {
    let mut cfg = TrainConfig::from_file(path)?;
    let method = a.method.as_deref().map(str::parse).transpose();
    let method = method.map_err(|e| anyhow::anyhow!("--method {e}"))?;
    let macaw_preset = a.macaw_preset.map(|p| match p {
        MacawPresetArg::Official => pdt_rundir::config::macaw::Preset::Official,
        MacawPresetArg::Promptdt => pdt_rundir::config::macaw::Preset::Promptdt,
    });
    let overrides = Overrides {
        seed: a.seed,
        iterations: a.iterations,
        method,
        macaw_preset,
        device: a.device,
        matmul: a.matmul,
        data: a.data.clone(),
    };
    cfg.apply(&overrides, |env| pdt_envs::family(env).map(|f| f.preset().prompt_length))?;
    Ok(cfg)
}
