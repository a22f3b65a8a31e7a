//! Running a plan: datasets first (each collected once, atomically), then every unfinished run as a
//! child process of the `promptdt` binary (`train --config` for a new run, `train --resume` for a
//! killed one), at most `jobs` at a time. A killed sweep resumes where it stopped: finished runs are
//! skipped, partial ones resume from their last checkpoint.
//!
//! Child processes rather than threads: libtorch's random generator and thread pool are global to a
//! process, so runs in one process could not be seeded independently or given their own cores.

mod schedule;

pub use crate::exec_types::{ExecOptions, ExecSummary, Progress, Stage, DIE_WITH_PARENT};
use crate::plan::{self, DataSpec, Plan, RunSpec, RunState};
use crate::ReproError;
use schedule::Scheduler;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

/// Collects `d` unless its `dataset.json` is there: into a temporary directory beside it, renamed
/// into place at the end, so a killed collection leaves nothing half-written and two processes
/// collecting the same data (identical bytes) cannot collide.
///
/// While it collects, this process holds a lock on `.<name>.tmp-<pid>.lock` beside the temporary
/// directory: a later `reproduce` removes a temporary directory whose lock is free (its collector
/// is dead, [`remove_stale_data_temps`]) and leaves a live one alone.
pub fn ensure_data(d: &DataSpec, opts: &ExecOptions) -> Result<bool, ReproError> {
    if let Some(p) = &d.prepared {
        return check_prepared(d, p).map(|()| false);
    }
    if d.dir.join("dataset.json").is_file() {
        return Ok(false);
    }
    let parent = d.dir.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent)
        .map_err(|e| ReproError::Io { path: parent.into(), source: e })?;
    let name = d.dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    let lock_path = lock_path_of(&tmp);
    // Our own pid's name: no other live process uses it, so this cannot be held elsewhere.
    let lock = pdt_base::fs::try_lock_file(&lock_path)
        .and_then(|l| {
            l.ok_or_else(|| std::io::Error::new(std::io::ErrorKind::WouldBlock, "held elsewhere"))
        })
        .map_err(|e| ReproError::Io { path: lock_path.clone(), source: e })?;
    let result = collect_into(d, &tmp, opts);
    let _ = std::fs::remove_dir_all(&tmp);
    let _ = std::fs::remove_file(&lock_path);
    drop(lock);
    result
}

/// A suite's data, made by the user's collection step, are there (at least one dataset file; the
/// training checks every file it reads, naming it); else an error saying what makes them.
fn check_prepared(d: &DataSpec, p: &crate::plan::Prepared) -> Result<(), ReproError> {
    let present = std::fs::read_dir(&d.dir).is_ok_and(|entries| {
        entries.flatten().any(|e| e.file_name().to_string_lossy().ends_with(".safetensors"))
    });
    if present {
        return Ok(());
    }
    let how = match &p.collect {
        Some(c) => format!("make them first: {c}"),
        None => "make them first with your collection step (promptdt.write_dataset, or \
                 `promptdt data import`)"
            .to_string(),
    };
    Err(ReproError::Invalid(format!(
        "suite {}: no datasets in {} (the manifest's suites.{}.data): reproduce does not collect \
         a suite's data; {how}",
        d.env,
        d.dir.display(),
        d.env
    )))
}

fn collect_into(d: &DataSpec, tmp: &Path, opts: &ExecOptions) -> Result<bool, ReproError> {
    let _ = std::fs::remove_dir_all(tmp);
    let mut cmd = Command::new(&opts.exe);
    cmd.arg(DIE_WITH_PARENT).args(["collect", "--env", &d.env, "--out"]).arg(tmp);
    // Families with scripted policies collect from those; the others from their committed agents.
    // An unknown family collects nothing either way: `collect` names it.
    let scripted = pdt_envs::family(&d.env).is_ok_and(|f| f.scripted().is_some());
    if !scripted {
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
    let (stdin, _parent_end) = parent_pipe(&opts.exe)?;
    let out = cmd
        .stdin(stdin)
        .output()
        .map_err(|e| ReproError::Io { path: opts.exe.clone(), source: e })?;
    if !out.status.success() {
        return Err(ReproError::Child {
            what: format!("collecting {} into {}", d.env, d.dir.display()),
            message: String::from_utf8_lossy(&out.stderr).trim().to_string(),
        });
    }
    if let Err(e) = std::fs::rename(tmp, &d.dir) {
        // Another process finished the same collection first: its files are the same.
        if !d.dir.join("dataset.json").is_file() {
            return Err(ReproError::Io { path: d.dir.clone(), source: e });
        }
    }
    Ok(true)
}

/// A pipe whose read end is a child's standard input and whose write end this process keeps (and
/// never writes to) for as long as the child should live. std opens both ends close-on-exec, so no
/// other child inherits the write end and keeps a sibling alive.
fn parent_pipe(exe: &Path) -> Result<(Stdio, std::io::PipeWriter), ReproError> {
    let (reader, writer) =
        std::io::pipe().map_err(|e| ReproError::Io { path: exe.to_path_buf(), source: e })?;
    Ok((reader.into(), writer))
}

/// The lock file of a temporary data directory: `.<name>.tmp-<pid>.lock` beside it.
fn lock_path_of(tmp: &Path) -> PathBuf {
    let mut name = tmp.file_name().unwrap_or_default().to_os_string();
    name.push(".lock");
    tmp.with_file_name(name)
}

/// Whether `name` is a temporary data directory's name, `.<name>.tmp-<pid>`.
fn is_data_temp(name: &str) -> bool {
    let Some(rest) = name.strip_prefix('.') else { return false };
    let Some((stem, pid)) = rest.rsplit_once(".tmp-") else { return false };
    !stem.is_empty() && !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit())
}

/// Removes the temporary data directories in `root` that a killed `reproduce` left behind (their
/// lock is free: the kernel released it when the collector died), with their lock files; a
/// collection in progress in another process holds its lock and is left alone. Returns the
/// directories removed.
pub fn remove_stale_data_temps(root: &Path) -> Result<Vec<PathBuf>, ReproError> {
    let entries = match std::fs::read_dir(root) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(ReproError::Io { path: root.into(), source: e }),
    };
    let mut removed = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| ReproError::Io { path: root.into(), source: e })?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let path = entry.path();
        // Only directories of our own naming: `--data-root` may hold other things.
        if !is_data_temp(name) || !path.is_dir() {
            continue;
        }
        let lock_path = lock_path_of(&path);
        // Held (by its live collector): leave it. Ours is kept until the tree is gone.
        let Some(_lock) = pdt_base::fs::try_lock_file(&lock_path)
            .map_err(|e| ReproError::Io { path: lock_path.clone(), source: e })?
        else {
            continue;
        };
        match std::fs::remove_dir_all(&path) {
            Ok(()) => removed.push(path),
            // Its collector renamed it into place between our listing and our lock.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(ReproError::Io { path, source: e }),
        }
        let _ = std::fs::remove_file(&lock_path);
    }
    Ok(removed)
}

fn write_atomic(path: &Path, text: &str) -> Result<(), ReproError> {
    let io = |e| ReproError::Io { path: path.to_path_buf(), source: e };
    if let Some(p) = path.parent() {
        std::fs::create_dir_all(p).map_err(io)?;
    }
    pdt_base::fs::write_atomic(path, text.as_bytes()).map_err(io)
}

/// The command line that runs (or resumes) one run. A run resumed in a copied or moved tree (or
/// with another `--data-root`) is pointed at the plan's data (`--data`): `train` checks that they
/// are the data the run trained on (their fingerprints) and records the new place.
fn command(spec: &RunSpec, state: RunState, opts: &ExecOptions) -> Result<Command, ReproError> {
    let mut cmd = Command::new(&opts.exe);
    cmd.arg(DIE_WITH_PARENT);
    match state {
        RunState::New => {
            cmd.arg("train").arg("--config").arg(&spec.config_path).arg("--out").arg(&spec.dir)
        }
        _ => {
            cmd.arg("train").arg("--resume").arg(&spec.dir);
            if plan::moved_data(spec)?.is_some() {
                cmd.arg("--data").arg(&spec.data.dir);
            }
            &mut cmd
        }
    };
    cmd.arg("--quiet");
    if let Some(p) = &opts.omp_wait_policy {
        cmd.env("OMP_WAIT_POLICY", p);
    }
    Ok(cmd)
}

/// A run claimed and read, about to be trained (alone or in a pack).
struct Member<'p> {
    index: usize,
    spec: &'p RunSpec,
    state: RunState,
    /// This process's claim on the run, held while the job runs.
    _claim: std::fs::File,
}

/// A child process training one run, or a pack of them.
struct Job<'p> {
    members: Vec<Member<'p>>,
    child: Child,
    log_path: PathBuf,
    /// The child's lifeline: it dies with this process (`DIE_WITH_PARENT`).
    _parent_end: std::io::PipeWriter,
}

/// The command line that trains `members` as one pack: their record written into a pack directory
/// under `out/packs/`, then `train --resume` of it (new runs start, partial ones resume). A moved
/// tree's runs are pointed at the plan's data, as [`command`] does for one.
fn pack_command(
    out: &Path,
    members: &[Member<'_>],
    opts: &ExecOptions,
) -> Result<Command, ReproError> {
    let specs: Vec<&RunSpec> = members.iter().map(|m| m.spec).collect();
    let dir = crate::packs::write_pack_dir(out, &specs, opts.pack_engine)?;
    let mut cmd = Command::new(&opts.exe);
    cmd.arg(DIE_WITH_PARENT).arg("train").arg("--resume").arg(&dir);
    let mut moved = None;
    for m in members {
        moved = moved.or(plan::moved_data(m.spec)?.map(|_| m.spec.data.dir.clone()));
    }
    if let Some(d) = moved {
        cmd.arg("--data").arg(d);
    }
    cmd.arg("--quiet");
    if let Some(p) = &opts.omp_wait_policy {
        cmd.env("OMP_WAIT_POLICY", p);
    }
    Ok(cmd)
}

/// Iterations a run has finished, from the line count of its `metrics.jsonl` (cheap to poll).
fn iterations_done(spec: &RunSpec) -> u64 {
    std::fs::read(pdt_rundir::RunDir::at(&spec.dir).metrics_path())
        .map(|b| b.iter().filter(|&&c| c == b'\n').count() as u64)
        .unwrap_or(0)
        .min(spec.config.train.iterations)
}

/// The name of the lock a `reproduce` process holds on a run directory while its child trains
/// there (beside `train`'s own `.lock`, which the child takes: one process cannot hold that for
/// another).
pub const CLAIM_FILE: &str = ".reproduce.lock";

/// Takes a run for this process: `None` when another process has it, either another `reproduce`
/// (its claim, [`CLAIM_FILE`]) or a `train` of its own (the run directory's `.lock`). The claim is
/// held until the returned file is dropped; the kernel releases it when this process dies.
fn claim(spec: &RunSpec) -> Result<Option<std::fs::File>, ReproError> {
    let dir = &spec.dir;
    std::fs::create_dir_all(dir).map_err(|e| ReproError::Io { path: dir.clone(), source: e })?;
    let path = dir.join(CLAIM_FILE);
    let Some(file) = pdt_base::fs::try_lock_file(&path)
        .map_err(|e| ReproError::Io { path: path.clone(), source: e })?
    else {
        return Ok(None);
    };
    // A `train` run by hand on this directory: probe its lock, and let go of it at once (the
    // child takes it).
    match pdt_base::fs::DirLock::try_acquire(dir) {
        Ok(probe) => drop(probe),
        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return Ok(None),
        Err(e) => return Err(ReproError::Io { path: dir.join(".lock"), source: e }),
    }
    Ok(Some(file))
}

/// Runs the plan's datasets and unfinished runs; `only` restricts it to one run key, or several
/// separated by commas (a pack's runs, as `--emit jobs --pack` writes them).
///
/// A run another process holds (another `reproduce` on the same `--out`, or a `train` on its
/// directory) is waited for, not run twice: once it is free, it is counted as finished if the
/// other process finished it, and resumed if not (that process was stopped).
pub fn execute(
    plan: &Plan,
    only: Option<&str>,
    opts: &ExecOptions,
    progress: &mut dyn FnMut(&Progress),
) -> Result<ExecSummary, ReproError> {
    let runs = selected(plan, only)?;
    // Variants are evaluated once the training is done: they need their base runs' weights.
    let (variants, runs): (Vec<&RunSpec>, Vec<&RunSpec>) =
        runs.into_iter().partition(|r| r.base.is_some());
    for v in &variants {
        plan::state(v)?;
    }
    // Check every existing run before starting anything: a mismatch is an error up front.
    let states = runs.iter().map(|r| plan::state(r)).collect::<Result<Vec<_>, _>>()?;
    let done: Vec<u64> = runs.iter().map(|r| iterations_done(r)).collect();
    let removed_temps = prepare_data(plan, &runs, &states, opts, &done, progress)?;
    let mut s = Scheduler::new(plan, opts, &runs, &states, done);
    s.summary.removed_temps = removed_temps;
    s.run(progress)?;
    crate::variant::evaluate(plan, &variants, opts, &mut s.summary)?;
    progress(&s.progress(Stage::Done));
    Ok(s.summary)
}

/// The plan's runs `only` names (keys separated by commas), or all of them.
fn selected<'p>(plan: &'p Plan, only: Option<&str>) -> Result<Vec<&'p RunSpec>, ReproError> {
    let Some(keys) = only else { return Ok(plan.runs.iter().collect()) };
    keys.split(',')
        .map(|k| {
            plan.runs.iter().find(|r| r.key == k).ok_or_else(|| ReproError::UnknownRun {
                key: k.into(),
                known: plan.runs.iter().map(|r| r.key.clone()).collect(),
            })
        })
        .collect()
}

/// Removes what a killed `reproduce` left of its collections (its `collect` child died with it),
/// then collects the data of the unfinished runs, each once. Returns the temporaries removed.
fn prepare_data(
    plan: &Plan,
    runs: &[&RunSpec],
    states: &[RunState],
    opts: &ExecOptions,
    done: &[u64],
    progress: &mut dyn FnMut(&Progress),
) -> Result<Vec<PathBuf>, ReproError> {
    let mut data: Vec<DataSpec> = Vec::new();
    for (r, s) in runs.iter().zip(states) {
        if *s != RunState::Finished && !data.contains(&r.data) {
            data.push(r.data.clone());
        }
    }
    let mut roots: Vec<PathBuf> = Vec::new();
    // A suite's data directory is the user's: nothing of reproduce's is ever left there.
    for d in plan.data().into_iter().filter(|d| d.prepared.is_none()) {
        if let Some(root) = d.dir.parent() {
            if !roots.iter().any(|r| r == root) {
                roots.push(root.to_path_buf());
            }
        }
    }
    let mut removed = Vec::new();
    for root in &roots {
        removed.extend(remove_stale_data_temps(root)?);
    }
    for d in &data {
        progress(&Progress {
            stage: Stage::Data(d.env.clone()),
            runs_total: runs.len(),
            runs_finished: 0,
            iterations_done: done.iter().sum(),
            iterations_total: runs.iter().map(|r| r.config.train.iterations).sum(),
            running: Vec::new(),
            waiting: Vec::new(),
        });
        ensure_data(d, opts)?;
    }
    Ok(removed)
}

/// Writes one self-contained command per run (`jobs.txt`, for `xargs -P` or any scheduler) and a
/// Slurm array script (`run.slurm`) into `dir`. Each command runs `reproduce --only` for one run, so
/// it collects its data if missing, starts or resumes the run, and writes no report; `reproduce
/// --report-only` merges the results from the run directories alone.
///
/// With `opts.pack` > 1, one command per pack instead (`--only` naming its runs, comma-separated;
/// the runs grouped as [`execute`] groups them: `crate::packs::group`); `extra_args` then carries
/// `--pack`. `opts.exe` is the binary the commands run; the datasets a command would collect from
/// `opts.pretrained_root`'s agents must have one there ([`check_agents`]), or nothing is written:
/// every task would fail on its node. `opts.jobs` is not used (the scheduler decides).
pub fn emit_jobs(
    plan: &Plan,
    dir: &Path,
    opts: &ExecOptions,
    manifest_arg: &str,
    extra_args: &[String],
) -> Result<Vec<PathBuf>, ReproError> {
    check_agents(plan, &opts.pretrained_root)?;
    let (exe, pack) = (opts.exe.as_path(), opts.pack);
    let q = |s: &str| format!("'{}'", s.replace('\'', r"'\''"));
    let mut lines = String::new();
    // Variants are left to the `reproduce` call after the jobs (they need the trained weights).
    let runs: Vec<&RunSpec> = plan.runs.iter().filter(|r| r.base.is_none()).collect();
    let groups = crate::packs::group(&runs, pack.max(1));
    for g in &groups {
        let keys: Vec<&str> = g.iter().map(|r| r.key.as_str()).collect();
        let mut parts = vec![
            q(&exe.to_string_lossy()),
            "reproduce".into(),
            q(manifest_arg),
            "--budget".into(),
            q(&plan.budget),
            "--out".into(),
            q(&plan.out.to_string_lossy()),
            "--only".into(),
            q(&keys.join(",")),
        ];
        parts.extend(extra_args.iter().map(|a| q(a)));
        lines.push_str(&parts.join(" "));
        lines.push('\n');
    }
    let jobs = dir.join("jobs.txt");
    write_atomic(&jobs, &lines)?;
    let slurm = dir.join("run.slurm");
    let n = groups.len();
    let unit = if pack > 1 { "pack" } else { "run" };
    let cpus = groups.iter().map(|g| task_cpus(g)).max().unwrap_or(1);
    let gpu = runs.iter().any(|r| r.config.run.device == pdt_base::device::DeviceSpec::Cuda);
    // A site names its GPUs, partitions and accounts its own way: the one line to edit is marked.
    let gres = match gpu {
        true => {
            "# --device cuda: one GPU per task. The place to edit for a site: its GPU type\n\
                 # (--gres=gpu:a100:1), partition (--partition=gpu), account, time limit.\n\
                 #SBATCH --gres=gpu:1\n"
        }
        false => "",
    };
    write_atomic(
        &slurm,
        &format!(
            "#!/bin/bash\n# One array task per {unit} of {exp} at the {budget} budget ({n} {unit}s).\n\
             # Submit: sbatch --array=1-{n} {slurm}\n\
             # Then:   {exe} reproduce {exp} --budget {budget} --out {out} --report-only\n\
             #SBATCH --job-name=promptdt-{exp}-{budget}\n\
             # The CPUs a task computes on: {cpus_why}.\n\
             #SBATCH --cpus-per-task={cpus}\n{gres}\
             set -euo pipefail\n\
             cmd=$(sed -n \"${{SLURM_ARRAY_TASK_ID}}p\" {jobs})\n\
             eval \"$cmd\"\n",
            exp = plan.experiment,
            budget = plan.budget,
            slurm = q(&slurm.to_string_lossy()),
            exe = q(&exe.to_string_lossy()),
            out = q(&plan.out.to_string_lossy()),
            jobs = q(&jobs.to_string_lossy()),
            cpus_why = match unit {
                "pack" => "its runs' --threads, times the runs of a pack computing at once",
                _ => "its run's --threads",
            },
        ),
    )?;
    Ok(vec![jobs, slurm])
}

/// The CPUs one emitted task keeps busy: its runs' libtorch threads (`run.threads`); a pack's runs
/// compute one at a time (one engine call for all, or each run's step in turn: docs/packs.md).
fn task_cpus(group: &[&RunSpec]) -> usize {
    group.iter().map(|r| pdt_base::threads(r.config.run.threads)).max().unwrap_or(1).max(1)
}

/// Refuses a plan whose datasets, not collected yet, would be collected from committed agents that
/// are not in `pretrained_root` (`<env>/agent.json`), naming the first one missing. Scripted
/// families need none.
pub fn check_agents(plan: &Plan, pretrained_root: &Path) -> Result<(), ReproError> {
    for d in plan.data() {
        let scripted = pdt_envs::family(&d.env).is_ok_and(|f| f.scripted().is_some());
        if scripted || d.prepared.is_some() || d.dir.join("dataset.json").is_file() {
            continue;
        }
        let agent = pretrained_root.join(&d.env).join("agent.json");
        if !agent.is_file() {
            return Err(ReproError::Invalid(format!(
                "--pretrained-root {}: no {} to collect the {} datasets ({}) with; give the \
                 directory of the committed agents (`pretrained/` in the checkout)",
                pretrained_root.display(),
                agent.display(),
                d.env,
                d.dir.display()
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stale_data_temps_go_and_live_ones_stay() {
        let d = tempfile::tempdir().expect("tempdir");
        let names = [".cheetah_dir-e2.tmp-123", ".ant_dir.tmp-456", "cheetah_dir-e2", ".x.tmp-abc"];
        for n in names {
            std::fs::create_dir(d.path().join(n)).expect("mkdir");
        }
        // A collection in progress in another process: it holds its lock.
        let live = std::fs::File::create(d.path().join(".ant_dir.tmp-456.lock")).expect("lock");
        live.try_lock().expect("locked");
        let removed = remove_stale_data_temps(d.path()).expect("cleanup");
        assert_eq!(removed, vec![d.path().join(".cheetah_dir-e2.tmp-123")]);
        assert!(!d.path().join(".cheetah_dir-e2.tmp-123.lock").exists());
        for n in &names[1..] {
            assert!(d.path().join(n).is_dir(), "{n} was removed");
        }
        assert!(remove_stale_data_temps(&d.path().join("missing")).expect("none").is_empty());
        assert!(is_data_temp(".point_robot-e2.tmp-9") && !is_data_temp(".tmp-9"));
        assert!(!is_data_temp("point_robot.tmp-9") && !is_data_temp(".a.tmp-"));
    }
}
