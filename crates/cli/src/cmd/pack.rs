//! `promptdt train --pack` and `promptdt train --resume <pack directory>`: argument handling and
//! display; the pack is one library call (`pdt_pack`).

use crate::args::TrainArgs;
use crate::cmd::bar;
use anyhow::{bail, Result};
use indicatif::{MultiProgress, ProgressBar};
use pdt_pack::PackOptions;
use pdt_rundir::config::{Overrides, TrainConfig};
use pdt_rundir::pack::Engine;
use pdt_train::run::{Progress, ResumeWith};

/// Whether `train` is asked for a pack: `--pack`, or `--resume` of a pack directory.
pub fn is_pack(a: &TrainArgs) -> bool {
    !a.pack.is_empty() || a.resume.as_deref().is_some_and(pdt_rundir::pack::is_pack_dir)
}

/// Starts (`--pack`) or resumes (`--resume` of a pack directory) a pack, one progress bar per run,
/// then each run's outcome; fails if any run failed.
pub fn train_pack(a: &TrainArgs) -> Result<()> {
    let engine =
        a.engine.as_deref().map(str::parse::<Engine>).transpose().map_err(anyhow::Error::msg)?;
    // An old script's `--pack-eval together` still runs: a note rather than an error, since the
    // runs' results are the same (within the batched engine's tolerance) and only the time their
    // evaluations take could differ, which measured the same (docs/packs.md).
    if a.pack_eval.as_deref() == Some("together") {
        eprintln!(
            "note: --pack-eval together is no longer an option: a pack's runs evaluate apart, each \
             with its own model (docs/packs.md)"
        );
    }
    let multi = MultiProgress::new();
    if a.quiet {
        multi.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let bars: std::sync::Mutex<Vec<ProgressBar>> = std::sync::Mutex::new(Vec::new());
    let progress = |slot: usize, p: &Progress| {
        let mut bars = bars.lock().unwrap_or_else(|e| e.into_inner());
        while bars.len() <= slot {
            let n = bars.len();
            let pb = multi.add(bar(0, &format!("run {n} {{bar:30}} {{pos}}/{{len}} it {{msg}}")));
            bars.push(pb);
        }
        let pb = &bars[slot];
        pb.set_length(p.iterations);
        pb.set_position(p.iteration);
        if let Some(r) = p.test_return {
            pb.set_message(format!("loss {:.5}  test return {r:.2}", p.loss));
        }
    };
    let resume_with =
        ResumeWith { iterations: a.iterations, device: a.device, data: a.data.clone() };
    let opts = PackOptions {
        resume: false,
        resume_with: ResumeWith::default(),
        stop_after_iterations: a.stop_after_iterations,
        engine,
        progress: &progress,
    };
    let (results, out) = match (&a.resume, &a.out) {
        (Some(dir), _) => {
            let opts = PackOptions { resume_with, ..opts };
            (pdt_pack::resume_pack_dir(dir, opts)?, dir.clone())
        }
        (None, Some(out)) => {
            let overrides = Overrides {
                seed: None,
                iterations: a.iterations,
                method: None,
                macaw_preset: None,
                device: a.device,
                matmul: a.matmul,
                data: a.data.clone(),
            };
            let mut configs = Vec::with_capacity(a.pack.len());
            for path in &a.pack {
                let mut cfg = TrainConfig::from_file(path)?;
                cfg.apply(&overrides, |env| {
                    pdt_envs::family(env).map(|f| f.preset().prompt_length)
                })?;
                configs.push(cfg);
            }
            (pdt_pack::train_pack_dir(configs, out, opts)?, out.clone())
        }
        (None, None) => bail!("--pack needs --out (the pack directory)"),
    };
    for pb in bars.lock().unwrap_or_else(|e| e.into_inner()).iter() {
        pb.finish_and_clear();
    }
    let mut failed = 0;
    for (slot, r) in results.iter().enumerate() {
        match r {
            Ok(s) => out!("run {slot}: {s}"),
            Err(e) => {
                failed += 1;
                out!("run {slot}: failed: {e}");
            }
        }
    }
    out!("pack directory: {}", out.display());
    if failed > 0 {
        bail!("{failed} of the pack's {} runs failed (the others went on)", results.len());
    }
    Ok(())
}
