//! Running a plan: datasets first (each collected once, atomically), then every unfinished run as a
//! child process of the `promptdt` binary (`train --config` for a new run, `train --resume` for a
//! killed one), at most `jobs` at a time. A killed sweep resumes where it stopped: finished runs are
//! skipped, partial ones resume from their last checkpoint.
//!
//! Child processes rather than threads: libtorch's random generator and thread pool are global to a
//! process, so runs in one process could not be seeded independently or given their own cores.

use crate::plan::{self, DataSpec, Plan, RunSpec, RunState};
use crate::ReproError;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// How to run a plan.
#[derive(Debug, Clone)]
pub struct ExecOptions {
    /// The `promptdt` binary the children run.
    pub exe: PathBuf,
    /// Runs at once.
    pub jobs: usize,
    /// `OMP_WAIT_POLICY` given to the children (`PASSIVE`: idle OpenMP threads sleep rather than
    /// spin, which matters when runs share cores; see BENCHMARKS.md).
    pub omp_wait_policy: Option<String>,
    /// Directory holding `pretrained/<env>/` agents (for `collect --from-pretrained`).
    pub pretrained_root: PathBuf,
}

/// What the progress callback sees.
#[derive(Debug, Clone)]
pub struct Progress {
    pub stage: Stage,
    pub runs_total: usize,
    pub runs_finished: usize,
    /// Training iterations done and planned, over every run of the plan.
    pub iterations_done: u64,
    pub iterations_total: u64,
    /// Keys of the runs in progress.
    pub running: Vec<String>,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Stage {
    Data(String),
    Training,
    Done,
}

/// What [`execute`] did.
#[derive(Debug, Clone, Default)]
pub struct ExecSummary {
    pub already_finished: usize,
    pub started: usize,
    pub resumed: usize,
    /// `(run key, message)` for every run whose process failed; the others still ran.
    pub failed: Vec<(String, String)>,
}

/// Collects `d` unless its `dataset.json` is there: into a temporary directory beside it, renamed
/// into place at the end, so a killed collection leaves nothing half-written and two processes
/// collecting the same data (identical bytes) cannot collide.
pub fn ensure_data(d: &DataSpec, opts: &ExecOptions) -> Result<bool, ReproError> {
    if d.dir.join("dataset.json").is_file() {
        return Ok(false);
    }
    let parent = d.dir.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent)
        .map_err(|e| ReproError::Io { path: parent.into(), source: e })?;
    let name = d.dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let mut cmd = Command::new(&opts.exe);
    cmd.args(["collect", "--env", &d.env, "--out"]).arg(&tmp);
    // Families with scripted policies collect from those; the others from their committed agents.
    if pdt_envs::collect_scripted::ScriptedFamily::from_name(&d.env).is_none() {
        cmd.arg("--from-pretrained").arg("--pretrained-dir").arg(opts.pretrained_root.join(&d.env));
    }
    if let Some(e) = d.episodes {
        cmd.args(["--episodes", &e.to_string()]);
    }
    if let Some(e) = d.prompt_episodes {
        cmd.args(["--prompt-episodes", &e.to_string()]);
    }
    if let Some(p) = &opts.omp_wait_policy {
        // Spinning OpenMP threads make a collection 20x slower when other processes are
        // runnable (measured: 19.7 s against 1.0 s for the smoke datasets of Cheetah-Dir).
        cmd.env("OMP_WAIT_POLICY", p);
    }
    let out = cmd
        .stdin(Stdio::null())
        .output()
        .map_err(|e| ReproError::Io { path: opts.exe.clone(), source: e })?;
    if !out.status.success() {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(ReproError::Child {
            what: format!("collecting {} into {}", d.env, d.dir.display()),
            message: String::from_utf8_lossy(&out.stderr).trim().to_string(),
        });
    }
    if let Err(e) = std::fs::rename(&tmp, &d.dir) {
        let _ = std::fs::remove_dir_all(&tmp);
        // Another process finished the same collection first: its files are the same.
        if !d.dir.join("dataset.json").is_file() {
            return Err(ReproError::Io { path: d.dir.clone(), source: e });
        }
    }
    Ok(true)
}

fn write_atomic(path: &Path, text: &str) -> Result<(), ReproError> {
    let io = |e| ReproError::Io { path: path.to_path_buf(), source: e };
    if let Some(p) = path.parent() {
        std::fs::create_dir_all(p).map_err(io)?;
    }
    pdt_base::fs::write_atomic(path, text.as_bytes()).map_err(io)
}

/// The command line that runs (or resumes) one run.
fn command(spec: &RunSpec, state: RunState, opts: &ExecOptions) -> Command {
    let mut cmd = Command::new(&opts.exe);
    match state {
        RunState::New => {
            cmd.arg("train").arg("--config").arg(&spec.config_path).arg("--out").arg(&spec.dir)
        }
        _ => cmd.arg("train").arg("--resume").arg(&spec.dir),
    };
    cmd.arg("--quiet");
    if let Some(p) = &opts.omp_wait_policy {
        cmd.env("OMP_WAIT_POLICY", p);
    }
    cmd
}

/// Iterations a run has finished, from the line count of its `metrics.jsonl` (cheap to poll).
fn iterations_done(spec: &RunSpec) -> u64 {
    std::fs::read(spec.dir.join("metrics.jsonl"))
        .map(|b| b.iter().filter(|&&c| c == b'\n').count() as u64)
        .unwrap_or(0)
        .min(spec.config.train.iterations)
}

/// Runs the plan's datasets and unfinished runs; `only` restricts it to one run key.
pub fn execute(
    plan: &Plan,
    only: Option<&str>,
    opts: &ExecOptions,
    progress: &mut dyn FnMut(&Progress),
) -> Result<ExecSummary, ReproError> {
    let runs: Vec<&RunSpec> = match only {
        Some(k) => {
            let r =
                plan.runs.iter().find(|r| r.key == k).ok_or_else(|| ReproError::UnknownRun {
                    key: k.into(),
                    known: plan.runs.iter().map(|r| r.key.clone()).collect(),
                })?;
            vec![r]
        }
        None => plan.runs.iter().collect(),
    };
    // Check every existing run before starting anything: a mismatch is an error up front.
    let states = runs.iter().map(|r| plan::state(r)).collect::<Result<Vec<_>, _>>()?;
    let total: u64 = runs.iter().map(|r| r.config.train.iterations).sum();
    let mut summary = ExecSummary::default();
    // Iterations done per run: read once here, then only for the runs in progress (a paper sweep
    // has dozens of metrics files of thousands of lines; the finished ones do not change).
    let mut done: Vec<u64> = runs.iter().map(|r| iterations_done(r)).collect();
    let report = |stage: Stage, finished: usize, running: Vec<String>, done: &[u64]| Progress {
        stage,
        runs_total: runs.len(),
        runs_finished: finished,
        iterations_done: done.iter().sum(),
        iterations_total: total,
        running,
    };

    let mut data: Vec<DataSpec> = Vec::new();
    for (r, s) in runs.iter().zip(&states) {
        if *s != RunState::Finished && !data.contains(&r.data) {
            data.push(r.data.clone());
        }
    }
    for d in &data {
        progress(&report(Stage::Data(d.env.clone()), 0, Vec::new(), &done));
        ensure_data(d, opts)?;
    }

    let mut queue: Vec<(usize, &RunSpec, RunState)> = Vec::new();
    for (i, (r, s)) in runs.iter().zip(&states).enumerate() {
        match s {
            RunState::Finished => summary.already_finished += 1,
            RunState::Partial { .. } => {
                summary.resumed += 1;
                queue.push((i, r, *s));
            }
            RunState::New => {
                summary.started += 1;
                let text = r
                    .config
                    .to_toml()
                    .map_err(|e| ReproError::Invalid(format!("run {}: {e}", r.key)))?;
                write_atomic(&r.config_path, &text)?;
                queue.push((i, r, *s));
            }
        }
    }
    queue.reverse(); // pop() takes them in plan order
    let mut running: Vec<(usize, &RunSpec, Child)> = Vec::new();
    let mut finished = summary.already_finished;
    let mut last = Instant::now() - Duration::from_secs(10);
    loop {
        while running.len() < opts.jobs.max(1) {
            let Some((index, spec, state)) = queue.pop() else { break };
            if let Some(p) = spec.log_path.parent() {
                std::fs::create_dir_all(p)
                    .map_err(|e| ReproError::Io { path: p.into(), source: e })?;
            }
            let log = std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(&spec.log_path)
                .map_err(|e| ReproError::Io { path: spec.log_path.clone(), source: e })?;
            let err = log
                .try_clone()
                .map_err(|e| ReproError::Io { path: spec.log_path.clone(), source: e })?;
            let child = command(spec, state, opts)
                .stdin(Stdio::null())
                .stdout(log)
                .stderr(err)
                .spawn()
                .map_err(|e| ReproError::Io { path: opts.exe.clone(), source: e })?;
            running.push((index, spec, child));
        }
        if running.is_empty() {
            break;
        }
        let mut i = 0;
        while i < running.len() {
            match running[i].2.try_wait() {
                Ok(Some(status)) => {
                    let (index, spec, _) = running.swap_remove(i);
                    done[index] = iterations_done(spec);
                    finished += 1;
                    if !status.success() {
                        let tail = std::fs::read_to_string(&spec.log_path).unwrap_or_default();
                        let tail: Vec<&str> = tail.lines().rev().take(5).collect();
                        summary.failed.push((
                            spec.key.clone(),
                            format!(
                                "{status}; last lines of {}: {}",
                                spec.log_path.display(),
                                tail.into_iter().rev().collect::<Vec<_>>().join(" | ")
                            ),
                        ));
                    }
                }
                Ok(None) => i += 1,
                Err(e) => return Err(ReproError::Io { path: running[i].1.dir.clone(), source: e }),
            }
        }
        if last.elapsed() >= Duration::from_secs(2) {
            for (index, spec, _) in &running {
                done[*index] = iterations_done(spec);
            }
            progress(&report(
                Stage::Training,
                finished,
                running.iter().map(|(_, s, _)| s.key.clone()).collect(),
                &done,
            ));
            last = Instant::now();
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    progress(&report(Stage::Done, finished, Vec::new(), &done));
    Ok(summary)
}

/// Writes one self-contained command per run (`jobs.txt`, for `xargs -P` or any scheduler) and a
/// Slurm array script (`run.slurm`) into `dir`. Each command runs `reproduce --only` for one run, so
/// it collects its data if missing, starts or resumes the run, and writes no report; `reproduce
/// --report-only` merges the results from the run directories alone.
pub fn emit_jobs(
    plan: &Plan,
    dir: &Path,
    exe: &Path,
    manifest_arg: &str,
    extra_args: &[String],
) -> Result<Vec<PathBuf>, ReproError> {
    let q = |s: &str| format!("'{}'", s.replace('\'', r"'\''"));
    let mut lines = String::new();
    for r in &plan.runs {
        let mut parts = vec![
            q(&exe.to_string_lossy()),
            "reproduce".into(),
            q(manifest_arg),
            "--budget".into(),
            q(&plan.budget),
            "--out".into(),
            q(&plan.out.to_string_lossy()),
            "--only".into(),
            q(&r.key),
        ];
        parts.extend(extra_args.iter().map(|a| q(a)));
        lines.push_str(&parts.join(" "));
        lines.push('\n');
    }
    let jobs = dir.join("jobs.txt");
    write_atomic(&jobs, &lines)?;
    let slurm = dir.join("run.slurm");
    let n = plan.runs.len();
    write_atomic(
        &slurm,
        &format!(
            "#!/bin/bash\n# One array task per run of {exp} at the {budget} budget ({n} runs).\n\
             # Submit: sbatch --array=1-{n} {slurm}\n\
             # Then:   {exe} reproduce {exp} --budget {budget} --out {out} --report-only\n\
             #SBATCH --job-name=promptdt-{exp}-{budget}\n#SBATCH --cpus-per-task=2\n\
             set -euo pipefail\n\
             cmd=$(sed -n \"${{SLURM_ARRAY_TASK_ID}}p\" {jobs})\n\
             eval \"$cmd\"\n",
            exp = plan.experiment,
            budget = plan.budget,
            slurm = q(&slurm.to_string_lossy()),
            exe = q(&exe.to_string_lossy()),
            out = q(&plan.out.to_string_lossy()),
            jobs = q(&jobs.to_string_lossy()),
        ),
    )?;
    Ok(vec![jobs, slurm])
}
