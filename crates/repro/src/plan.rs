//! Expanding a manifest at a budget into ordinary run directories with their training
//! configurations, and reading how far each run is.
//!
//! Layout under the output directory (`--out`, default `runs/repro`):
//!
//! ```text
//! data/<env>[-e<episodes>]/          datasets (collect --from-pretrained, or scripted for point_robot;
//!                                    a manifest's suite names its own data directory instead)
//! runs/<cell id>/<budget>/seed<N>/   one ordinary run directory per (cell, budget, seed)
//! configs/<cell id>__<budget>__seed<N>.toml   the configuration each run was started from
//! logs/<same name>.log               the run's own output
//! reports/<experiment>-<budget>/     the report
//! ```
//!
//! A run directory depends only on the cell's id, the budget and the seed, so experiments that
//! share a cell (Figure 2's Prompt-DT and Table 1's 1 x 5 prompt) share its runs; before a run is
//! reused its recorded configuration must equal the one this manifest asks for.

use crate::manifest::{Cell, Manifest};
use crate::ReproError;
use pdt_base::device::{DeviceSpec, Matmul};
use pdt_rundir::config::TrainConfig;
use pdt_rundir::RunDir;
use std::path::{Path, PathBuf};

/// Where the datasets of one environment come from and go.
#[derive(Debug, Clone, PartialEq)]
pub struct DataSpec {
    pub env: String,
    pub dir: PathBuf,
    pub episodes: Option<usize>,
    pub prompt_episodes: Option<usize>,
    /// A suite's data (`[suites.<env>]`): made by the user's own collection step, which this
    /// names (its `collect`, if given); never collected by `reproduce`, only checked to be there.
    pub prepared: Option<Prepared>,
}

/// Data a manifest's suite names (`[suites.<name>] data`), made before `reproduce` runs.
#[derive(Debug, Clone, PartialEq)]
pub struct Prepared {
    /// The manifest's `[suites.<name>] collect`: the command that makes them, in words.
    pub collect: Option<String>,
}

/// One run of the plan.
#[derive(Debug, Clone)]
pub struct RunSpec {
    /// `<cell id>/<budget>/seed<N>`: what `--only` takes.
    pub key: String,
    pub cell: usize,
    pub seed: u64,
    pub dir: PathBuf,
    pub config_path: PathBuf,
    pub log_path: PathBuf,
    pub config: TrainConfig,
    pub data: DataSpec,
    /// A variant's run (`crate::variant`): the trained run it evaluates, not trains. `config` is
    /// that run's with the variant's `[eval]` merged in.
    pub base: Option<crate::variant_spec::BaseRun>,
}

/// A cell that is not run at this budget, and why.
#[derive(Debug, Clone)]
pub struct Skipped {
    pub cell: usize,
    pub reason: String,
}

#[derive(Debug, Clone)]
pub struct Plan {
    pub experiment: String,
    pub budget: String,
    pub out: PathBuf,
    pub runs: Vec<RunSpec>,
    pub skipped: Vec<Skipped>,
}

impl Plan {
    /// Every distinct dataset directory the runs need.
    pub fn data(&self) -> Vec<DataSpec> {
        let mut v: Vec<DataSpec> = Vec::new();
        for r in &self.runs {
            if !v.contains(&r.data) {
                v.push(r.data.clone());
            }
        }
        v
    }

    pub fn report_dir(&self) -> PathBuf {
        self.out.join("reports").join(format!("{}-{}", self.experiment, self.budget))
    }
}

/// How far a run directory is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RunState {
    New,
    Partial { iteration: u64 },
    Finished,
}

/// What a plan needs besides the manifest.
#[derive(Debug, Clone)]
pub struct PlanOptions {
    pub budget: String,
    /// Run directories, configurations, logs and reports go under it.
    pub out: PathBuf,
    /// Datasets go under it (default `<out>/data`).
    pub data_root: PathBuf,
    /// Each run's libtorch thread count and device (recorded in its configuration; neither is part
    /// of a run's identity, so a run may be resumed with others).
    pub threads: usize,
    pub device: DeviceSpec,
    /// Each run's `run.matmul` (part of a run's identity: a run recorded with another is refused
    /// by name rather than resumed with products computed another way).
    pub matmul: Matmul,
    /// Overrides every cell's seed count.
    pub seeds: Option<u32>,
}

/// Expands `m` at a budget into runs.
pub fn plan(m: &Manifest, o: &PlanOptions) -> Result<Plan, ReproError> {
    let (budget, out, data_root) = (o.budget.as_str(), o.out.as_path(), o.data_root.as_path());
    m.budget(budget)?;
    let mut runs = Vec::new();
    let mut skipped = Vec::new();
    for (i, cell) in m.cells.iter().enumerate() {
        if let Some(reason) = &cell.pending {
            skipped.push(Skipped { cell: i, reason: reason.clone() });
            continue;
        }
        // A variant runs where its base cell runs, on its runs: their data, seeds and training.
        let base = m.base_of(cell).map_err(|message| ReproError::Manifest {
            origin: m.name.clone(),
            message: format!("cell {}: {message}", cell.id()),
        })?;
        let trained = base.map_or(cell, |(_, b)| b);
        if let Some(reason) = base.and_then(|(_, b)| b.pending.as_ref()) {
            let reason = format!("its base cell {} is pending ({reason})", trained.id());
            skipped.push(Skipped { cell: i, reason });
            continue;
        }
        let s = m.settings(budget, trained)?;
        let own = m.settings(budget, cell)?;
        if s.run == Some(false) || own.run == Some(false) {
            skipped.push(Skipped { cell: i, reason: format!("not run at the {budget} budget") });
            continue;
        }
        let data = match m.suites.get(&cell.env) {
            // A suite's data are where the manifest says: the user's collection step made them
            // (episode counts are that step's, so `data_episodes` does not apply).
            Some(suite) => DataSpec {
                env: cell.env.clone(),
                dir: suite.data.clone(),
                episodes: None,
                prompt_episodes: None,
                prepared: Some(Prepared { collect: suite.collect.clone() }),
            },
            None => DataSpec {
                env: cell.env.clone(),
                dir: data_root.join(match s.data_episodes {
                    Some(e) => format!("{}-e{e}", cell.env),
                    None => cell.env.clone(),
                }),
                episodes: s.data_episodes,
                prompt_episodes: s.prompt_set_episodes,
                prepared: None,
            },
        };
        let family = m.family_name(&cell.env);
        let n = o.seeds.or(s.seeds).unwrap_or(3);
        for seed in 0..u64::from(n) {
            let key = format!("{}/{budget}/seed{seed}", cell.id());
            let flat = key.replace('/', "__");
            let mut config = config_for(trained, &family, &s, seed, o.threads, &data.dir)?;
            config.run.device = o.device;
            config.run.matmul = o.matmul;
            let mut variant = None;
            if let (Some(_), Some(eval)) = (base, &cell.eval) {
                let base_key = format!("{}/{budget}/seed{seed}", trained.id());
                let invalid = |e: String| ReproError::Invalid(format!("cell {}: {e}", cell.id()));
                // A rule naming the variant's cell may give it its own episode count (the cited
                // bandit's rollouts); the base cell's settings give the rest.
                if let Some(e) = own.eval_episodes {
                    config.eval.episodes = e;
                }
                config = crate::variant_spec::with_eval(&config, eval).map_err(invalid)?;
                config.validate().map_err(|e| invalid(e.to_string()))?;
                variant = Some(crate::variant_spec::BaseRun {
                    dir: out.join("runs").join(&base_key),
                    key: base_key,
                    eval: eval.clone(),
                    repeats: own.eval_repeats.unwrap_or(1),
                });
            }
            runs.push(RunSpec {
                dir: out.join("runs").join(&key),
                config_path: out.join("configs").join(format!("{flat}.toml")),
                log_path: out.join("logs").join(format!("{flat}.log")),
                key,
                cell: i,
                seed,
                config,
                data: data.clone(),
                base: variant,
            });
        }
    }
    Ok(Plan {
        experiment: m.name.clone(),
        budget: budget.into(),
        out: out.to_path_buf(),
        runs,
        skipped,
    })
}

/// The training configuration of one run: the reference code's defaults (as `configs/` has them),
/// the cell's variant, then the budget's settings. `family` is the family the cell's `env` stands
/// for ([`Manifest::family_name`]: a suite's file path, or the built-in family's name).
pub fn config_for(
    cell: &Cell,
    family: &str,
    s: &crate::manifest::Settings,
    seed: u64,
    threads: usize,
    data_dir: &Path,
) -> Result<TrainConfig, ReproError> {
    let method = cell
        .method
        .parse::<pdt_rundir::config::Method>()
        .map_err(|_| ReproError::Invalid(format!("unknown method {:?}", cell.method)))?;
    let mut c = TrainConfig::default();
    c.run.method = method;
    c.run.seed = seed;
    c.run.threads = threads;
    c.env.name = family.to_string();
    c.env.split = cell.split.clone().unwrap_or_else(|| "default".into());
    c.data.dir = data_dir.to_path_buf();
    let d = cell.dataset.clone().unwrap_or_else(|| "expert".into());
    c.data.dataset_mode = d.clone();
    c.data.prompt_mode = d.clone();
    c.data.test_dataset_mode = d.clone();
    c.data.test_prompt_mode = cell.test_prompt.clone().unwrap_or(d);
    if let Some([j, h]) = cell.prompt {
        c.sampler.prompt_episodes = j;
        c.sampler.prompt_length = Some(h);
    }
    if let Some(p) = &cell.prompt_position {
        c.sampler.prompt_position =
            toml::Value::String(p.clone()).try_into().map_err(|e: toml::de::Error| {
                ReproError::Invalid(format!("cell {}: prompt_position: {e}", cell.id()))
            })?;
    }
    if let Some(b) = cell.finetune_batch {
        c.eval.finetune_batch = b;
    }
    if let Some(n) = cell.finetune_steps {
        c.eval.finetune_steps = n;
    }
    if let Some(v) = s.iterations {
        c.train.iterations = v;
    }
    if let Some(v) = s.steps_per_iteration {
        c.train.steps_per_iteration = v;
    }
    if let Some(v) = s.batch_size_per_task {
        c.sampler.batch_size_per_task = v;
    }
    if let Some(v) = s.eval_episodes {
        c.eval.episodes = v;
    }
    if let Some(v) = s.test_eval_interval {
        c.train.test_eval_interval = v;
    }
    if let Some(v) = s.train_eval_interval {
        c.train.train_eval_interval = v;
    }
    if let Some(v) = s.save_interval {
        c.train.save_interval = v;
    }
    if let Some(v) = s.resume_interval {
        c.train.resume_interval = v;
    }
    if let Some(v) = s.finetune_batch {
        c.eval.finetune_batch = v;
    }
    if let Some(v) = s.learning_rate {
        c.optim.learning_rate = v;
    }
    if let Some(v) = s.warmup_steps {
        c.optim.warmup_steps = v;
    }
    if let Some(v) = s.finetune_steps {
        c.eval.finetune_steps = v;
    }
    if method == pdt_rundir::config::Method::Macaw {
        // The Prompt-DT paper's MACAW protocol by default: its table's settings, adapted on as
        // many transitions as the prompt has steps (K* = J x H) with 10 steps. The cell's and the
        // budget's fine-tuning data and steps are MACAW's adaptation data and steps.
        let family = pdt_envs::family(&c.env.name)
            .map_err(|e| ReproError::Invalid(format!("cell {}: {e}", cell.id())))?;
        c.macaw = pdt_rundir::config::macaw::MacawConfig::preset(
            s.macaw_preset.unwrap_or(pdt_rundir::config::macaw::Preset::Promptdt),
            c.prompt_steps(family.preset().prompt_length),
        );
        for b in [cell.finetune_batch, s.finetune_batch].into_iter().flatten() {
            c.macaw.adapt_batch = b;
        }
        for n in [cell.finetune_steps, s.finetune_steps].into_iter().flatten() {
            c.macaw.adapt_steps = n as usize;
        }
        if let Some(w) = s.macaw_width {
            c.macaw.width = w;
        }
        if let Some(b) = s.macaw_batch {
            c.macaw.inner_batch = b;
            c.macaw.outer_batch = b;
        }
        if let Some(k) = s.macaw_buffer_skip {
            c.macaw.buffer_skip = k;
        }
    }
    c.validate().map_err(|e| ReproError::Invalid(format!("cell {}: {e}", cell.id())))?;
    Ok(c)
}

/// A configuration without what does not change a run's meaning (its thread count), as TOML.
///
/// Of the data directory only its name (`<env>[-e<episodes>]`, which says what was collected) is
/// kept: where a tree's data lie is not part of a run's identity. A run records its data
/// directory as an absolute path, so a copied or moved tree (or one read with another
/// `--data-root`) names a place that is gone or belongs to another tree; what matters is the
/// data's content, which is checked by its fingerprint ([`check_data`]; `train --resume --data`
/// checks it too).
fn identity(c: &TrainConfig) -> toml::Value {
    let mut c = c.clone();
    c.run.threads = 0;
    c.run.device = DeviceSpec::default();
    // How often a resume point is written changes no result (resuming is byte-identical).
    c.train.resume_interval = 0;
    c.data.dir = c.data.dir.file_name().map(PathBuf::from).unwrap_or_default();
    // A suite's runs record the suite file's absolute path: like the data directory, only its
    // name is the run's, so that an archived run (`results render`, `--report-only`) or a moved
    // tree still reads as its cell's where the checkout lies elsewhere. Its content is checked
    // where it matters: a resumed run against its copy, the data by their fingerprints.
    if pdt_envs::suite::is_suite_path(&c.env.name) {
        let name = Path::new(&c.env.name).file_name().map(|n| n.to_string_lossy().into_owned());
        c.env.name = name.unwrap_or_default();
    }
    // As written to config.toml: a method's configuration carries only its own sections.
    c.to_toml_value().unwrap_or(toml::Value::Boolean(false))
}

/// A run's recorded configuration (`config.toml`); the error names the file.
fn read_config(dir: &Path) -> Result<TrainConfig, String> {
    RunDir::at(dir).config().map_err(|e| e.to_string())
}

/// `p` with symbolic links and `..` resolved where it exists (two spellings of one directory
/// compare equal), as given otherwise.
fn canonical(p: &Path) -> PathBuf {
    std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf())
}

/// The data directory a run's `config.toml` records, when it is not the one the plan gives it
/// (the tree was copied or moved, or `--data-root` names another place): resuming the run must
/// then point it at the plan's (`train --resume --data`), and a finished run's data are checked by
/// fingerprint. `None` when they are the same place or the run has no `config.toml` yet.
pub fn moved_data(spec: &RunSpec) -> Result<Option<PathBuf>, ReproError> {
    if !RunDir::at(&spec.dir).config_path().is_file() {
        return Ok(None);
    }
    let recorded = read_config(&spec.dir).map_err(ReproError::Invalid)?;
    Ok((canonical(&recorded.data.dir) != canonical(&spec.data.dir)).then_some(recorded.data.dir))
}

/// Fingerprints of the data in the plan's data directories, computed once per directory, task
/// list and kind of data (a paper sweep has dozens of runs on the same data).
#[derive(Debug, Default)]
pub struct DataCheck {
    fingerprints: std::collections::BTreeMap<String, Result<String, String>>,
}

impl DataCheck {
    /// Checks that the plan's data of `spec` are the data the run trained on: the content
    /// fingerprints it recorded in `task_stats.json` (runs made before fingerprints were recorded
    /// have none, and pass). Only runs whose data moved are checked ([`moved_data`]); for the
    /// others the data are where the run found them. `Err` says what differs, naming the files.
    pub fn check(&mut self, spec: &RunSpec) -> Result<(), String> {
        let Some(was) = moved_data(spec).map_err(|e| e.to_string())? else { return Ok(()) };
        // No data here at all (a tree copied without them): nothing to mistake for the run's
        // data; the report names the missing card where it needs it.
        if !spec.data.dir.is_dir() {
            return Ok(());
        }
        let run = RunDir::at(&spec.dir);
        let stats_path = run.stats_path();
        let stats = run.stats().map_err(|e| e.to_string())?;
        let c = read_config(&spec.dir)?;
        // The plan's suite file, not the one the run recorded: an archived run's may lie in
        // another checkout (its identity, the name, was checked).
        let family = pdt_envs::family(&spec.config.env.name).map_err(|e| e.to_string())?;
        let (train, test) = family.split(&c.env.split).map_err(|e| e.to_string())?;
        let sets = [
            (
                "training",
                train,
                &c.data.dataset_mode,
                &c.data.prompt_mode,
                &stats.train_data_fingerprint,
            ),
            (
                "test",
                test,
                &c.data.test_dataset_mode,
                &c.data.test_prompt_mode,
                &stats.test_data_fingerprint,
            ),
        ];
        for (which, tasks, dataset_mode, prompt_mode, recorded) in sets {
            if recorded.is_empty() {
                continue;
            }
            let key = format!(
                "{}|{}|{tasks:?}|{dataset_mode}|{prompt_mode}|{:?}",
                spec.data.dir.display(),
                family.name(),
                c.data.format
            );
            let now = self
                .fingerprints
                .entry(key)
                .or_insert_with(|| {
                    let ds = pdt_data::multitask::DatasetSpec {
                        dir: spec.data.dir.clone(),
                        env: family.name().to_string(),
                        tasks: tasks.clone(),
                        dataset_mode: dataset_mode.clone(),
                        prompt_mode: prompt_mode.clone(),
                        format: c.data.format,
                    };
                    pdt_data::multitask::load_multitask(&ds)
                        .map(|d| d.fingerprint())
                        .map_err(|e| e.to_string())
                })
                .clone()?;
            if &now != recorded {
                return Err(format!(
                    "the {which} data in {} differ from what the run trained on in {} ({}: \
                     {recorded}, now {now}); --data-root names where the run's data are",
                    spec.data.dir.display(),
                    was.display(),
                    stats_path.display()
                ));
            }
        }
        Ok(())
    }
}

/// Keys whose values differ between two TOML documents (dotted paths).
fn differing(a: &toml::Value, b: &toml::Value, at: &str, out: &mut Vec<String>) {
    match (a, b) {
        (toml::Value::Table(x), toml::Value::Table(y)) => {
            let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
            for k in keys {
                let path = if at.is_empty() { k.clone() } else { format!("{at}.{k}") };
                match (x.get(k), y.get(k)) {
                    (Some(p), Some(q)) => differing(p, q, &path, out),
                    _ => out.push(path),
                }
            }
        }
        _ if a != b => out.push(format!("{at} ({a} vs {b})")),
        _ => {}
    }
}

/// The keys (dotted paths, with both values) in which a run's recorded configuration differs from
/// the one a plan gives it, apart from what is not part of a run's identity (paths, device,
/// threads, how often resume points are written; see `identity`).
pub fn config_differences(recorded: &TrainConfig, planned: &TrainConfig) -> Vec<String> {
    let mut diff = Vec::new();
    differing(&identity(recorded), &identity(planned), "", &mut diff);
    diff
}

/// The state of a variant's run: finished once its `variant.json` is there (checked against the
/// configuration the plan gives it, as a trained run's is), new otherwise.
fn variant_state(spec: &RunSpec) -> Result<RunState, ReproError> {
    if !spec.dir.join(crate::variant_spec::VARIANT_JSON).is_file() {
        return Ok(RunState::New);
    }
    let recorded = RunDir::at(&spec.dir).config()?;
    let diff = config_differences(&recorded, &spec.config);
    if !diff.is_empty() {
        return Err(ReproError::ConfigMismatch { dir: spec.dir.clone(), keys: diff.join(", ") });
    }
    Ok(RunState::Finished)
}

/// The state of a run directory, after checking that a run already there was started from the
/// same configuration (apart from the thread count).
pub fn state(spec: &RunSpec) -> Result<RunState, ReproError> {
    if spec.base.is_some() {
        return variant_state(spec);
    }
    let run = RunDir::at(&spec.dir);
    let latest = run.latest_path();
    if !latest.exists() {
        // A run that reached its end lost its commit record (a copy that left it out): it is
        // neither new (starting it again would overwrite its logs) nor running.
        if let Some(evidence) = reached_end(spec) {
            return Err(ReproError::Invalid(format!(
                "{}: the run reached its last iteration ({evidence}), but {} is missing; restore \
                 it, or move the run away to start it again",
                spec.dir.display(),
                latest.display()
            )));
        }
        return Ok(RunState::New);
    }
    let recorded = read_config(&spec.dir).map_err(ReproError::Invalid)?;
    let mut diff = Vec::new();
    differing(&identity(&recorded), &identity(&spec.config), "", &mut diff);
    if !diff.is_empty() {
        return Err(ReproError::ConfigMismatch { dir: spec.dir.clone(), keys: diff.join(", ") });
    }
    // Removed between the two looks: as if it had never been there.
    let Some(l) = run.latest()? else { return Ok(RunState::New) };
    Ok(if l.iteration >= spec.config.train.iterations {
        RunState::Finished
    } else {
        RunState::Partial { iteration: l.iteration }
    })
}

/// What shows that a run without `checkpoints/latest.json` reached its last iteration, if
/// anything does: an evaluation of that iteration or its metrics line.
fn reached_end(spec: &RunSpec) -> Option<String> {
    let n = spec.config.train.iterations;
    let run = RunDir::at(&spec.dir);
    // Unreadable logs show nothing; the report names them where it reads them.
    let evals = run.eval_lines().ok().flatten();
    if evals.and_then(|l| l.rows.iter().map(|l| l.iteration).max()).is_some_and(|i| i >= n) {
        return Some(format!("eval.jsonl has iteration {n}'s evaluation"));
    }
    let metrics = run.metrics().ok().flatten();
    if metrics.and_then(|l| l.rows.iter().map(|l| l.iteration).max()).is_some_and(|i| i >= n) {
        return Some(format!("metrics.jsonl has iteration {n}"));
    }
    None
}
