//! `promptdt reproduce --emit jobs` (one command per run or pack, for a scheduler) and `--status`
//! (where each run stands): both end with the command that goes on.

use crate::args::ReproduceArgs;
use anyhow::Result;
use pdt_repro::sweep::JobFlags;
use pdt_repro::{exec, plan, status, Plan, Sweep};

/// Writes the jobs (jobs.txt and a Slurm array script) and says how to run them and what after.
pub fn emit(
    a: &ReproduceArgs,
    name: &str,
    p: &Plan,
    sweep: &Sweep,
    eopts: &exec::ExecOptions,
    opts: &plan::PlanOptions,
) -> Result<()> {
    let out = &opts.out;
    let dir = out.join("jobs").join(format!("{}-{}", p.experiment, p.budget));
    let flags = JobFlags {
        device: a.device,
        matmul: a.matmul,
        omp_wait_policy: &a.omp_wait_policy,
        data_root: a.data_root.is_some().then_some(opts.data_root.as_path()),
        pretrained_root: &eopts.pretrained_root,
    };
    // A manifest given as a file is named by its absolute path, so the jobs run from anywhere.
    let manifest = match std::path::Path::new(name).is_file() {
        true => std::path::absolute(name)?.to_string_lossy().into_owned(),
        false => name.to_string(),
    };
    let files = exec::emit_jobs(p, &dir, eopts, &manifest, &sweep.job_args(&flags))?;
    let names: Vec<String> = files.iter().map(|f| f.display().to_string()).collect();
    out!("{} runs; wrote {}", p.runs.len(), names.join(", "));
    out!("run them, e.g.: xargs -P 2 -I{{}} sh -c {{}} < {}", files[0].display());
    let variants = p.runs.iter().filter(|r| r.base.is_some()).count();
    let then =
        format!("then: promptdt reproduce {name} --budget {} --out {}", p.budget, out.display());
    if variants > 0 {
        // Variants evaluate the trained weights: after the jobs, not beside them.
        out!("{then} (evaluates the {variants} variant runs, then reports)");
    } else {
        out!("{then} --report-only");
    }
    Ok(())
}

/// The plan's runs and where each stands, then the command that goes on.
pub fn status(p: &Plan, a: &ReproduceArgs, name: &str) -> Result<()> {
    let runs = status::runs(p, &a.registry);
    out!("{}", status::table(&runs).trim_end());
    let t = status::Tally::of(&runs);
    out!("{}", t.summary(p, &a.registry));
    if t.unfinished() {
        // The same command without --status: it resumes the part-way runs and starts the rest.
        let mut cmd = format!("promptdt reproduce {name} --budget {}", p.budget);
        cmd.push_str(&format!(" --out {}", a.out.display()));
        if let Some(d) = &a.data_root {
            cmd.push_str(&format!(" --data-root {}", d.display()));
        }
        if let Some(n) = a.seeds {
            cmd.push_str(&format!(" --seeds {n}"));
        }
        out!("to go on (resumes the part-way runs, starts the rest): {cmd}");
    }
    Ok(())
}
