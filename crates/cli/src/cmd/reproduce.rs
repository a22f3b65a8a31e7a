//! `promptdt reproduce`: a paper table or figure. Lists the experiments, or plans one at a budget,
//! runs what is unfinished and reports it next to the paper; `--emit jobs` and `--status` are
//! `cmd::reproduce_jobs`.

use crate::args::ReproduceArgs;
use crate::cmd::{bar, reproduce_jobs};
use anyhow::{bail, Context, Result};
use pdt_repro::{exec, plan, report, Manifest, Plan, Stage, Sweep, SweepAsk, SweepDefaults};
use std::path::{Path, PathBuf};

pub fn reproduce(a: &ReproduceArgs) -> Result<()> {
    if a.list {
        for e in pdt_repro::list()? {
            out!("{e}");
        }
        return Ok(());
    }
    let Some(name) = a.experiment.as_deref() else { bail!("name an experiment, or --list") };
    let m = Manifest::load(name)?;
    let on_gpu = matches!(pdt_torch::device::resolve(a.device), Ok(d) if d.is_cuda());
    // Refused here rather than by each run after its data are collected. Emitted jobs and reports
    // may be made on a machine without the GPU that will run them.
    let trains_here = !(a.report_only || a.status || a.emit.is_some());
    if a.matmul == pdt_base::device::Matmul::Tf32 && trains_here && !on_gpu {
        bail!(
            "--matmul tf32 needs a CUDA device, and --device {} is the CPU here (the CPU computes \
             float32 products in fp32 only)",
            a.device.as_str()
        );
    }
    if a.matmul == pdt_base::device::Matmul::Bf16 && trains_here {
        let device = pdt_torch::device::resolve(a.device)?;
        pdt_torch::device::bf16_allowed(device)?;
    }
    let sweep = sweep(a, on_gpu)?;
    let opts = plan_options(a, sweep.threads)?;
    let p = if a.report_only {
        // A fresh clone has no run directories: the registry's archived runs stand in for them.
        let (p, used) = pdt_repro::registry::plan_with_archive(&m, &opts, &a.registry)?;
        if !used.is_empty() {
            out!("{} runs read from the registry {}", used.len(), a.registry.display());
        }
        p
    } else {
        plan::plan(&m, &opts)?
    };
    if a.status {
        return reproduce_jobs::status(&p, a, name);
    }
    let eopts = exec::ExecOptions {
        exe: std::env::current_exe().context("the promptdt binary's path")?,
        jobs: sweep.jobs,
        omp_wait_policy: Some(a.omp_wait_policy.clone()),
        pretrained_root: pretrained_root(a.pretrained_root.as_deref())?,
        pack: sweep.pack,
        pack_engine: sweep.pack_engine,
    };
    match a.emit.as_deref() {
        Some("jobs") => return reproduce_jobs::emit(a, name, &p, &sweep, &eopts, &opts),
        Some(other) => bail!("--emit {other}: expected `jobs`"),
        None => {}
    }
    if !a.report_only {
        execute(a, &p, &eopts, &opts.out)?;
        if a.only.is_some() {
            return Ok(());
        }
    }
    // The reference's expert returns are committed in the manifests; `--reference DIR` recomputes
    // them from the release's prompt files instead, so a DIR that is not there is an error, not a
    // silent fallback to the committed numbers.
    if let Some(d) = a.reference.as_deref().filter(|d| !d.is_dir()) {
        bail!(
            "--reference {}: not a directory (the reference release's official-prompts/)",
            d.display()
        );
    }
    let r = report::report(&m, &p, a.reference.as_deref())?;
    out!("{}", r.markdown);
    out!("report: {}", p.report_dir().display());
    Ok(())
}

/// Runs at once, threads, packs and their engine: the device's defaults (`SweepDefaults`) with
/// what the flags ask.
fn sweep(a: &ReproduceArgs, on_gpu: bool) -> Result<Sweep> {
    let engine = a.pack_engine.as_deref().map(str::parse::<pdt_rundir::pack::Engine>);
    let ask = SweepAsk {
        jobs: a.jobs,
        threads: a.threads,
        pack: a.pack,
        pack_engine: engine.transpose().map_err(anyhow::Error::msg)?,
    };
    Ok(SweepDefaults::for_device(on_gpu).sweep(&ask))
}

/// The plan's options: the budget, the directories (absolute, so emitted jobs run from anywhere),
/// the threads per run, the device and the seeds.
fn plan_options(a: &ReproduceArgs, threads: usize) -> Result<plan::PlanOptions> {
    let out = std::path::absolute(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
    let data_root = match &a.data_root {
        Some(d) => {
            std::path::absolute(d).with_context(|| format!("--data-root {}", d.display()))?
        }
        None => out.join("data"),
    };
    Ok(plan::PlanOptions {
        budget: a.budget.clone(),
        out,
        data_root,
        threads,
        device: a.device,
        matmul: a.matmul,
        seeds: a.seeds,
    })
}

/// Runs the plan's unfinished runs (or `--only` those), with a progress bar; fails if any failed.
fn execute(a: &ReproduceArgs, p: &Plan, eopts: &exec::ExecOptions, out: &Path) -> Result<()> {
    let pb = bar(0, "{prefix} {bar:30} {pos}/{len} iterations [{elapsed} < {eta}] {msg}");
    pb.set_prefix(format!("{} {}", p.experiment, p.budget));
    let summary = exec::execute(p, a.only.as_deref(), eopts, &mut |pr| {
        if matches!(pr.stage, Stage::Training | Stage::Done) {
            pb.set_length(pr.iterations_total);
            pb.set_position(pr.iterations_done);
        }
        pb.set_message(pr.message());
    })?;
    pb.finish_and_clear();
    for t in &summary.removed_temps {
        out!("removed {}, left by a killed collection", t.display());
    }
    out!("{}: {summary}", p.experiment);
    for (k, msg) in &summary.failed {
        eprintln!("run {k} failed: {msg}");
    }
    if !summary.failed.is_empty() {
        let logs = out.join("logs");
        bail!("{} runs failed (logs under {})", summary.failed.len(), logs.display());
    }
    Ok(())
}

/// `--pretrained-root`, absolute: as given, else `pretrained` in this directory, else the
/// `pretrained/` of the checkout this binary was built in, so `reproduce`, and the jobs it emits for
/// other machines, find the committed agents from any directory (`exec::check_agents` refuses to
/// emit jobs whose agents are missing).
fn pretrained_root(given: Option<&Path>) -> Result<PathBuf> {
    let here = PathBuf::from("pretrained");
    let built = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../pretrained");
    let dir = match given {
        Some(d) => d.to_path_buf(),
        None if !here.is_dir() && built.is_dir() => built.canonicalize().unwrap_or(built),
        None => here,
    };
    std::path::absolute(&dir).with_context(|| format!("--pretrained-root {}", dir.display()))
}
