//! The results registry: finished runs' small files, committed in the repository
//! (`results/<cell id>/<budget>/seed<N>/`), so that a report can be written on a fresh clone with no
//! data and no checkpoints (`reproduce EXP --budget B --report-only` reads an archived run wherever
//! its run directory is absent).
//!
//! An archived run is an ordinary (if partial) run directory: `config.toml`, `run.json`,
//! `task_stats.json`, `eval.jsonl`, `eval_final.json` where the run has one,
//! `checkpoints/latest.json` (the commit record that says how far it got, without the weights it
//! names), `metrics.jsonl` thinned to at most [`MAX_METRICS_ROWS`] rows (every evaluated iteration's
//! and the last kept), plus two files of its own:
//!
//! - `normalisation.json`: the per-task expert and random returns of the dataset card the run
//!   was scored with ([`crate::baselines::baselines`]), so its normalised score needs no data;
//! - `provenance.json`: where and how it ran ([`Provenance`]), and for a user's experiment (a
//!   manifest file that is no built-in one) which manifest it belongs to, so that `results render`
//!   finds that experiment again without a flag ([`Provenance::manifest`]).
//!
//! `promptdt results add` ([`add`]) is the only writer: it refuses an unfinished run, one whose
//! configuration is not its cell's at that budget, one whose `metrics.jsonl` does not reach its
//! last iteration, and a `--date` that is no calendar day. `results render` refuses a registry
//! with a run it cannot read ([`archive_problems`], and what the report names).

use crate::baselines::{baselines, Normalisation, NORMALISATION_JSON};
use crate::manifest::{Manifest, BUILTIN};
use crate::plan::{self, Plan, PlanOptions};
use crate::ReproError;
use pdt_rundir::{MetricsLine, RunDir, RunInfo};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The archived run's provenance file.
pub const PROVENANCE_JSON: &str = "provenance.json";
/// The archived run's normalisation returns.
/// Rows of `metrics.jsonl` kept at most (plus the evaluated iterations'), so a run stays small.
pub const MAX_METRICS_ROWS: usize = 200;

/// Where and how an archived run ran. What the run directory records is read from it; the rest
/// (the machine, the build) comes from `results add`'s flags.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// `<cell id>/<budget>/seed<N>`.
    pub key: String,
    pub experiment: String,
    /// A user's experiment's manifest file (`results add --exp FILE`), which `results render`
    /// reads the experiment from: relative to [`registry_root`] (the repository root for
    /// `results/`) where the file lies under it, else absolute. Absent for a built-in experiment
    /// (compiled in), and in archives made before it was recorded (render names those).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub manifest: Option<String>,
    pub budget: String,
    /// The commit of the binary that trained it.
    pub commit: String,
    /// The device the run asked for (`config.toml`'s `run.device`).
    pub device: String,
    /// The GPU (or CPU) model that ran it.
    pub device_name: String,
    pub cpu: String,
    /// The libtorch build it was linked or run with.
    pub libtorch: String,
    pub threads: usize,
    pub iterations: u64,
    /// Training time of the run (`time/elapsed_s` of its last `metrics.jsonl` line).
    pub wall_time_s: f64,
    /// `solo` (one run per process) or `packed`.
    pub packing: String,
    /// How many runs shared the device at once (this one included).
    pub shared_with: u32,
    /// When it ran (`YYYY-MM-DD`).
    pub date: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
}

/// What `results add` is told about the runs beyond their directories.
#[derive(Debug, Clone, Default)]
pub struct ProvenanceFlags {
    pub commit: String,
    pub device_name: String,
    pub cpu: String,
    pub libtorch: String,
    pub packing: String,
    pub shared_with: u32,
    /// `YYYY-MM-DD`; `None`: the day `run.json` says the run was created.
    pub date: Option<String>,
    pub note: String,
}

/// `promptdt results add`.
#[derive(Debug, Clone)]
pub struct AddOptions {
    /// Run directories laid out as `reproduce` makes them (`.../<cell id>/<budget>/seed<N>`).
    pub runs: Vec<PathBuf>,
    pub experiment: String,
    pub budget: String,
    /// Where the runs' datasets (their cards) lie; `None`: where each run's `config.toml` says.
    pub data_root: Option<PathBuf>,
    pub registry: PathBuf,
    pub provenance: ProvenanceFlags,
}

/// One run added.
#[derive(Debug, Clone)]
pub struct Added {
    pub key: String,
    pub dir: PathBuf,
    pub bytes: u64,
}

/// `promptdt results add`'s line for the run.
impl std::fmt::Display for Added {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "archived {} into {} ({} bytes)", self.key, self.dir.display(), self.bytes)
    }
}

fn refuse(dir: &Path, why: impl std::fmt::Display) -> ReproError {
    ReproError::Invalid(format!("{}: not archived: {why}", dir.display()))
}

/// Adds every run of `o` to the registry (each written into a temporary directory renamed into
/// place, replacing an earlier archive of the same run). Stops at the first run refused.
pub fn add(o: &AddOptions) -> Result<Vec<Added>, ReproError> {
    // Checked before any run is archived: a provenance date that is no day is refused, not kept.
    if let Some(d) = &o.provenance.date {
        check_date(d).map_err(|why| ReproError::Invalid(format!("--date {d:?}: {why}")))?;
    }
    let m = Manifest::load(&o.experiment)?;
    let manifest = manifest_record(&o.experiment, &m, &o.registry)?;
    let mut added = Vec::new();
    for dir in &o.runs {
        added.push(add_one(&m, manifest.as_deref(), o, dir)?);
    }
    Ok(added)
}

/// Whether `name` is a built-in experiment's (compiled in: `results render` reads it without a
/// file).
pub fn is_builtin(name: &str) -> bool {
    BUILTIN.iter().any(|(n, _)| *n == name)
}

/// The directory a registry's recorded manifest paths are taken from: the one holding the registry
/// (the repository root for `results/`, where `RESULTS.md` is written), so that a checkout moved
/// or cloned elsewhere finds its manifests.
pub fn registry_root(registry: &Path) -> PathBuf {
    let abs = std::path::absolute(registry).unwrap_or_else(|_| registry.to_path_buf());
    let parent = abs.parent().map_or_else(|| abs.clone(), Path::to_path_buf);
    std::fs::canonicalize(&parent).unwrap_or(parent)
}

/// What `provenance.json` records as the manifest of `--exp exp` (read as `m`) archived into
/// `registry`: `None` for a built-in experiment, and for a manifest file named as one (its runs
/// are that experiment's, rendered with it); else the file's path from [`registry_root`] where it
/// lies under it, absolute where not.
fn manifest_record(exp: &str, m: &Manifest, registry: &Path) -> Result<Option<String>, ReproError> {
    if is_builtin(exp) || is_builtin(&m.name) {
        return Ok(None);
    }
    let file = std::fs::canonicalize(exp).map_err(|e| io(Path::new(exp), e))?;
    let root = registry_root(registry);
    let path = file.strip_prefix(&root).unwrap_or(&file);
    Ok(Some(path.to_string_lossy().into_owned()))
}

fn add_one(
    m: &Manifest,
    manifest: Option<&str>,
    o: &AddOptions,
    dir: &Path,
) -> Result<Added, ReproError> {
    let seed = dir
        .file_name()
        .and_then(|n| n.to_str())
        .and_then(|n| n.strip_prefix("seed"))
        .and_then(|n| n.parse::<u32>().ok())
        .ok_or_else(|| refuse(dir, "expected a directory `<cell id>/<budget>/seed<N>`"))?;
    // Every cell planned with this seed, so that a seed beyond the budget's count is found too.
    let opts = PlanOptions {
        budget: o.budget.clone(),
        out: PathBuf::new(),
        data_root: o.data_root.clone().unwrap_or_default(),
        threads: 1,
        device: Default::default(),
        matmul: Default::default(),
        seeds: Some(seed + 1),
    };
    let p = plan::plan(m, &opts)?;
    let spec = p
        .runs
        .iter()
        .find(|r| r.seed == u64::from(seed) && dir.ends_with(Path::new(&r.key)))
        .ok_or_else(|| {
            refuse(dir, format!("no run of {} at the {} budget ends this path", m.name, o.budget))
        })?;
    let run = RunDir::at(dir);
    let config = run.config()?;
    let diff = plan::config_differences(&config, &spec.config);
    if !diff.is_empty() {
        return Err(refuse(
            dir,
            format!("its config.toml is not {}'s planned one: {}", spec.key, diff.join(", ")),
        ));
    }
    let n = config.train.iterations;
    let done = run.latest()?.map_or(0, |l| l.iteration);
    if done < n {
        return Err(refuse(dir, format!("unfinished: {done} of {n} iterations")));
    }
    let evals = run.eval_lines()?.map(|l| l.rows).unwrap_or_default();
    let eval_iters: std::collections::BTreeSet<u64> =
        evals.iter().filter(|l| l.is_test()).map(|l| l.iteration).collect();
    if eval_iters.last().is_none_or(|&last| last < n) {
        return Err(refuse(dir, format!("eval.jsonl has no test evaluation of iteration {n}")));
    }
    let metrics = run.metrics()?;
    // A trained run's curve must reach the iteration its commit record says it reached: a
    // `metrics.jsonl` cut short (a copy taken while it was written, a lost or torn last line)
    // would be archived as a curve without its end, and its wall time read from an earlier row.
    // A variant trained nothing: its metrics are the base run's business.
    if spec.base.is_none() {
        check_metrics_reach(&run.metrics_path(), metrics.as_ref(), done)
            .map_err(|w| refuse(dir, w))?;
    }
    let metrics = metrics.map(|l| l.rows).unwrap_or_default();
    // A variant's time is its evaluation's (it trained nothing); its record names its files.
    let variant = match &spec.base {
        Some(_) => {
            let path = dir.join(crate::variant_spec::VARIANT_JSON);
            if !path.is_file() {
                return Err(refuse(dir, format!("a variant not evaluated: no {}", path.display())));
            }
            Some(pdt_rundir::read_json::<crate::variant_spec::VariantRecord>(&path)?)
        }
        None => None,
    };
    let wall_time_s = match &variant {
        Some(v) => v.seconds,
        None => metrics.last().map_or(f64::NAN, |l| l.elapsed_s),
    };
    let data_dir = match &o.data_root {
        Some(_) => spec.data.dir.clone(),
        None => config.data.dir.clone(),
    };
    let dataset =
        data_dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    // A suite's runs are scored with the suite's declared returns; where it declares none, with
    // its data's card if there is one (none: no task is normalised); a built-in family's with its
    // dataset card's.
    let norm = match crate::baselines::suite_baselines(&config.env.name, dir) {
        Some(Ok(b)) => Normalisation::from_baselines(
            format!("suite {} (its expert_return and random_return)", config.env.name),
            &b,
        ),
        Some(Err(_)) => match baselines(&data_dir) {
            Ok(b) => Normalisation::from_baselines(dataset, &b),
            Err(_) => Normalisation::from_baselines(dataset, &Default::default()),
        },
        None => Normalisation::from_baselines(dataset, &baselines(&data_dir)?),
    };
    let info = run.info()?;
    let date = match &o.provenance.date {
        Some(d) => d.clone(),
        None => created_date(&info).ok_or_else(|| {
            refuse(
                dir,
                format!("run.json's created {:?} is not unix:<seconds>; give --date", info.created),
            )
        })?,
    };
    let f = &o.provenance;
    let prov = Provenance {
        key: spec.key.clone(),
        experiment: m.name.clone(),
        manifest: manifest.map(str::to_string),
        budget: o.budget.clone(),
        commit: f.commit.clone(),
        device: config.run.device.as_str().to_string(),
        device_name: f.device_name.clone(),
        cpu: f.cpu.clone(),
        libtorch: f.libtorch.clone(),
        threads: config.run.threads,
        iterations: done,
        wall_time_s,
        packing: f.packing.clone(),
        shared_with: f.shared_with,
        date,
        note: f.note.clone(),
    };

    let target = o.registry.join(&spec.key);
    let archive = Archive {
        run: &run,
        variant: variant.as_ref(),
        metrics: thin(&metrics, &eval_iters),
        norm: &norm,
        prov: &prov,
    };
    let bytes = archive.write_to(&target, seed)?;
    Ok(Added { key: spec.key.clone(), dir: target, bytes })
}

/// A run's archive: its small files copied, its curve thinned, its normalisation and provenance.
struct Archive<'a> {
    run: &'a RunDir,
    variant: Option<&'a crate::variant_spec::VariantRecord>,
    metrics: Vec<MetricsLine>,
    norm: &'a Normalisation,
    prov: &'a Provenance,
}

impl Archive<'_> {
    /// Writes the archive into a temporary directory beside `target`, then renames it into place
    /// (replacing an earlier archive of the run). Returns its size in bytes.
    fn write_to(&self, target: &Path, seed: u32) -> Result<u64, ReproError> {
        let (run, dir) = (self.run, self.run.path());
        let parent = target.parent().unwrap_or(Path::new("."));
        std::fs::create_dir_all(parent).map_err(|e| io(parent, e))?;
        let tmp = parent.join(format!(".tmp-seed{seed}-{}", std::process::id()));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(|e| io(&tmp, e))?;
        }
        let out = RunDir::at(&tmp);
        out.create_dir()?;
        std::fs::create_dir_all(out.checkpoints_dir()).map_err(|e| io(&tmp, e))?;
        // Copied byte for byte: an old run's files keep their old names, which RunDir reads.
        let copies = [
            (run.config_path(), out.config_path()),
            (run.info_path(), out.info_path()),
            (run.stats_path(), out.stats_path()),
            (run.eval_path(), out.eval_path()),
            (run.latest_path(), out.latest_path()),
            (run.final_eval_path(), out.final_eval_path()),
        ];
        for (from, to) in copies {
            if from == run.final_eval_path() && !from.exists() {
                continue;
            }
            std::fs::copy(&from, &to).map_err(|e| io(&from, e))?;
        }
        if let Some(v) = self.variant {
            for name in [crate::variant_spec::VARIANT_JSON, v.result_file.as_str()] {
                let (from, to) = (dir.join(name), tmp.join(name));
                std::fs::copy(&from, &to).map_err(|e| io(&from, e))?;
            }
        }
        out.append_metrics(&self.metrics)?;
        pdt_rundir::write_json(&tmp.join(NORMALISATION_JSON), self.norm)?;
        pdt_rundir::write_json(&tmp.join(PROVENANCE_JSON), self.prov)?;
        let bytes = dir_bytes(&tmp);
        if target.exists() {
            let old = parent.join(format!(".old-seed{seed}-{}", std::process::id()));
            std::fs::rename(target, &old).map_err(|e| io(target, e))?;
            std::fs::rename(&tmp, target).map_err(|e| io(target, e))?;
            std::fs::remove_dir_all(&old).map_err(|e| io(&old, e))?;
        } else {
            std::fs::rename(&tmp, target).map_err(|e| io(target, e))?;
        }
        Ok(bytes)
    }
}

/// Why `metrics` (the rows of `path`) do not reach iteration `done`, if they do not.
fn check_metrics_reach(
    path: &Path,
    metrics: Option<&pdt_rundir::JsonLines<MetricsLine>>,
    done: u64,
) -> Result<(), String> {
    let Some(lines) = metrics else {
        return Err(format!("{} is missing (the run's training curve)", path.display()));
    };
    let last = lines.rows.iter().map(|r| r.iteration).max();
    if last.is_some_and(|l| l >= done) {
        return Ok(());
    }
    let missing = match last {
        Some(l) if l + 1 == done => format!("iteration {done} is missing"),
        Some(l) => format!("iterations {}..={done} are missing", l + 1),
        None => format!("it has no row (iterations 1..={done} are missing)"),
    };
    let torn = lines.skipped.as_ref().map_or(String::new(), |s| format!("; {s}"));
    Err(format!(
        "{} ends at iteration {}, but checkpoints/latest.json says the run reached {done}: \
         {missing} (cut short?){torn}",
        path.display(),
        last.unwrap_or(0)
    ))
}

/// Whether `d` is a calendar date written `YYYY-MM-DD` (the provenance's format), year 1970 on.
pub fn check_date(d: &str) -> Result<(), String> {
    let expected = "expected a calendar date YYYY-MM-DD, e.g. 2026-03-14";
    let b = d.as_bytes();
    let shaped = b.len() == 10
        && b[4] == b'-'
        && b[7] == b'-'
        && b.iter().enumerate().all(|(i, c)| i == 4 || i == 7 || c.is_ascii_digit());
    if !shaped {
        return Err(format!("not YYYY-MM-DD; {expected}"));
    }
    let num = |r: std::ops::Range<usize>| d[r].parse::<u32>().unwrap_or(0);
    let (y, m, day) = (num(0..4), num(5..7), num(8..10));
    if y < 1970 {
        return Err(format!("year {y} is before any run (1970 on); {expected}"));
    }
    let leap = (y % 4 == 0 && y % 100 != 0) || y % 400 == 0;
    let days = match m {
        1 | 3 | 5 | 7 | 8 | 10 | 12 => 31,
        4 | 6 | 9 | 11 => 30,
        2 if leap => 29,
        2 => 28,
        _ => return Err(format!("month {m} is not 01-12; {expected}")),
    };
    if !(1..=days).contains(&day) {
        return Err(format!("day {day} is not in {y}-{m:02}, which has {days} days; {expected}"));
    }
    Ok(())
}

fn io(path: &Path, source: std::io::Error) -> ReproError {
    ReproError::Io { path: path.to_path_buf(), source }
}

/// At most [`MAX_METRICS_ROWS`] evenly spaced rows, plus every evaluated iteration's (the report
/// shows the loss there) and the last.
fn thin(rows: &[MetricsLine], eval_iters: &std::collections::BTreeSet<u64>) -> Vec<MetricsLine> {
    let every = rows.len().div_ceil(MAX_METRICS_ROWS).max(1);
    rows.iter()
        .enumerate()
        .filter(|(i, r)| {
            i % every == 0 || *i + 1 == rows.len() || eval_iters.contains(&r.iteration)
        })
        .map(|(_, r)| r.clone())
        .collect()
}

fn dir_bytes(dir: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else { return 0 };
    entries
        .flatten()
        .map(|e| match e.metadata() {
            Ok(md) if md.is_dir() => dir_bytes(&e.path()),
            Ok(md) => md.len(),
            Err(_) => 0,
        })
        .sum()
}

/// `run.json`'s `created` (`unix:<seconds>`) as a UTC date.
fn created_date(info: &RunInfo) -> Option<String> {
    let secs: i64 = info.created.strip_prefix("unix:")?.parse().ok()?;
    Some(civil_date(secs.div_euclid(86_400)))
}

/// Days since 1970-01-01 as `YYYY-MM-DD` (Howard Hinnant's civil-from-days).
fn civil_date(days: i64) -> String {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!("{y:04}-{m:02}-{d:02}")
}

/// An archived run's provenance; an error names `provenance.json` and why it cannot be read.
pub fn provenance(run_dir: &Path) -> Result<Provenance, ReproError> {
    Ok(pdt_rundir::read_json::<Provenance>(&run_dir.join(PROVENANCE_JSON))?)
}

/// What cannot be read in the archived run in `dir` besides what the report reads and names
/// itself: its `provenance.json`, its `normalisation.json` (the report takes the first seed's
/// readable one, so another seed's corrupt one would pass unseen) and, for a trained run (not a
/// `variant`), a `metrics.jsonl` that reaches the iteration its commit record says (as
/// [`add`] checks it). Each names the file and why.
pub fn archive_problems(dir: &Path, variant: bool) -> Vec<String> {
    let mut out = Vec::new();
    if let Err(e) = provenance(dir) {
        out.push(e.to_string());
    }
    if let Err(e) = pdt_rundir::read_json::<Normalisation>(&dir.join(NORMALISATION_JSON)) {
        out.push(e.to_string());
    }
    let run = RunDir::at(dir);
    // An unreadable commit record or log is named by the report (the run's state, its loss).
    if let (false, Ok(Some(latest)), Ok(metrics)) = (variant, run.latest(), run.metrics()) {
        if let Err(why) =
            check_metrics_reach(&run.metrics_path(), metrics.as_ref(), latest.iteration)
        {
            out.push(why);
        }
    }
    out
}

/// Points every run of `plan` whose run directory is absent at its archive in `registry`, where
/// there is one. Returns the keys so substituted.
pub fn use_archived(plan: &mut Plan, registry: &Path) -> Vec<String> {
    let mut used = Vec::new();
    for r in &mut plan.runs {
        let archived = registry.join(&r.key);
        if !r.dir.exists() && archived.join(PROVENANCE_JSON).is_file() {
            r.dir = archived;
            used.push(r.key.clone());
        }
    }
    used
}

/// `m`'s plan for `--report-only`: a run whose directory is absent is read from its archive in
/// `registry`, and archived seeds beyond the budget's seed count join the plan (unless `--seeds`
/// says how many), so the report shows what `RESULTS.md` shows. Returns the plan and the keys of
/// the runs read from the registry.
pub fn plan_with_archive(
    m: &Manifest,
    opts: &PlanOptions,
    registry: &Path,
) -> Result<(Plan, Vec<String>), ReproError> {
    let mut p = plan::plan(m, opts)?;
    let max_archived = max_seed(&keys(registry), &opts.budget);
    if let (None, Some(max)) = (opts.seeds, max_archived) {
        let planned: std::collections::BTreeSet<String> =
            p.runs.iter().map(|r| r.key.clone()).collect();
        // Seeds per cell differ by group (table1: 3 on Cheetah-Dir, 1 elsewhere): expand to the
        // most of either, then keep the planned runs and the archived ones, so that an archive
        // of seed 1 does not cut a group planned with 3 seeds down to 2.
        let max_planned = p.runs.iter().map(|r| r.seed).max().unwrap_or(0);
        let seeds = u64::from(max).max(max_planned) + 1;
        let seeds = u32::try_from(seeds).unwrap_or(u32::MAX);
        p = plan::plan(m, &PlanOptions { seeds: Some(seeds), ..opts.clone() })?;
        p.runs.retain(|r| {
            planned.contains(&r.key) || registry.join(&r.key).join(PROVENANCE_JSON).is_file()
        });
    }
    let used = use_archived(&mut p, registry);
    Ok((p, used))
}

/// The highest seed among `keys` (`<cell id>/<budget>/seed<N>`) at `budget`.
pub fn max_seed<'a>(keys: impl IntoIterator<Item = &'a String>, budget: &str) -> Option<u32> {
    let at = format!("/{budget}/seed");
    keys.into_iter()
        .filter(|k| k.contains(&at))
        .filter_map(|k| k.rsplit_once("/seed").and_then(|(_, s)| s.parse::<u32>().ok()))
        .max()
}

/// Every archived run's key (`<cell id>/<budget>/seed<N>`) under `registry`, sorted.
pub fn keys(registry: &Path) -> Vec<String> {
    walk_runs(registry).0
}

/// Run directories under `registry` (`.../seed<N>`) without their `provenance.json`: [`keys`]
/// does not see them, so `results render` names them instead of leaving their runs out unsaid.
pub fn strays(registry: &Path) -> Vec<String> {
    walk_runs(registry).1
}

/// The registry's run directories, sorted: those with their `provenance.json` (archived) and the
/// `seed<N>` directories without it (strays).
fn walk_runs(registry: &Path) -> (Vec<String>, Vec<String>) {
    fn walk(dir: &Path, at: &Path, found: &mut (Vec<String>, Vec<String>)) {
        let Ok(entries) = std::fs::read_dir(dir) else { return };
        for e in entries.flatten() {
            let (p, name) = (e.path(), e.file_name());
            let text = name.to_string_lossy();
            if !p.is_dir() || text.starts_with('.') {
                continue;
            }
            let rel = at.join(&name);
            let key = || rel.to_string_lossy().into_owned();
            if p.join(PROVENANCE_JSON).is_file() {
                found.0.push(key());
            } else if text.strip_prefix("seed").is_some_and(|n| n.parse::<u32>().is_ok()) {
                found.1.push(key());
            } else {
                walk(&p, &rel, found);
            }
        }
    }
    let mut found = (Vec::new(), Vec::new());
    walk(registry, Path::new(""), &mut found);
    found.0.sort();
    found.1.sort();
    found
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A built-in experiment records no manifest; a manifest file records its path from the
    /// registry's directory where it lies under it, its absolute path where not.
    #[test]
    fn the_manifest_is_recorded_from_the_registrys_directory() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let fig2 = Manifest::load("fig2").expect("fig2");
        assert!(matches!(manifest_record("fig2", &fig2, tmp.path()), Ok(None)));
        let text = crate::manifest::BUILTIN[0].1.replace("name = \"fig2\"", "name = \"mine\"");
        let file = tmp.path().join("exp/mine.toml");
        std::fs::create_dir_all(file.parent().expect("parent")).expect("mkdir");
        std::fs::write(&file, text).expect("write");
        let path = file.to_str().expect("utf-8");
        let mine = Manifest::load(path).expect("mine");
        let at = |registry: &Path| manifest_record(path, &mine, registry).expect("recorded");
        assert_eq!(at(&tmp.path().join("results")).as_deref(), Some("exp/mine.toml"));
        let elsewhere = tmp.path().join("exp/sub/results");
        let abs = std::fs::canonicalize(&file).expect("canonical");
        assert_eq!(at(&elsewhere), Some(abs.to_string_lossy().into_owned()));
        // Named as a built-in experiment: that experiment's runs.
        assert_eq!(manifest_record(path, &fig2, tmp.path()).expect("fig2"), None);
    }

    #[test]
    fn dates_are_calendar_days() {
        for d in ["2026-03-14", "2024-02-29", "2000-02-29", "1970-01-01", "2026-12-31"] {
            assert_eq!(check_date(d), Ok(()), "{d}");
        }
        for (d, why) in [
            ("2026-13-45", "month 13"),
            ("yesterday", "not YYYY-MM-DD"),
            ("2026-1-5", "not YYYY-MM-DD"),
            ("2026-02-29", "day 29"),
            ("1900-02-29", "year 1900"),
            ("2026-04-31", "day 31"),
            ("2026-00-10", "month 0"),
            ("2026-01-00", "day 0"),
            ("+026-01-01", "not YYYY-MM-DD"),
        ] {
            let e = check_date(d).err().unwrap_or_default();
            assert!(e.contains(why), "{d}: {e}");
        }
        // What the default (run.json's day) writes passes the check.
        assert_eq!(check_date(&civil_date(20_000)), Ok(()));
    }

    #[test]
    fn civil_dates() {
        assert_eq!(civil_date(0), "1970-01-01");
        assert_eq!(civil_date(11_017), "2000-03-01");
        // unix:1795707986, the GPU runs' run.json
        assert_eq!(civil_date(1_795_707_986 / 86_400), "2026-11-26");
    }

    #[test]
    fn thinning_keeps_evaluations_and_the_last_row() {
        let rows: Vec<MetricsLine> = (1..=500)
            .map(|i| MetricsLine {
                iteration: i,
                step: i * 10,
                elapsed_s: i as f64,
                values: Default::default(),
            })
            .collect();
        let evals: std::collections::BTreeSet<u64> = [1, 101, 201, 301, 401, 500].into();
        let kept = thin(&rows, &evals);
        assert!(kept.len() <= MAX_METRICS_ROWS + evals.len(), "{}", kept.len());
        let iters: Vec<u64> = kept.iter().map(|r| r.iteration).collect();
        for e in &evals {
            assert!(iters.contains(e), "{e}");
        }
        assert_eq!(iters.last(), Some(&500));
    }
}
