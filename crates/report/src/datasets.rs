//! Dataset-quality report: the episode returns of a dataset directory written by
//! `promptdt collect`, per environment family and task, against the reference release's expert
//! returns, with the project's quality bars evaluated.
//!
//! Returns are always recomputed from the data files; `dataset.json` (the card) is only
//! cross-checked, so a stale or hand-edited card cannot make a dataset look better than it is.
//! How the numbers are computed and which bars apply is documented in `docs/report.md`
//! ("Dataset quality report").

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::fs;
use std::path::{Path, PathBuf};

use pdt_data::inspect::natural_cmp;
use pdt_data::native::{self, FILE_EXTENSION};
use pdt_data::reference::{load_pickle, ReferenceOptions};
use pdt_data::TaskDataset;

use crate::aggregate::file_stem;
use crate::error::ReportError;
use crate::plot::{self, Curve, Labels, XAxis, PALETTE};
use crate::render::{csv_line, md, num, warnings_markdown};
use crate::write_outputs;

/// What to report on and where to write it.
#[derive(Debug, Clone, Default)]
pub struct DatasetReportConfig {
    /// A dataset directory: `{env}-{task}-{mode}.safetensors` files (`.pkl` also accepted).
    pub ours: PathBuf,
    /// A directory of reference files (the reference release's pickles, or native files).
    pub reference: Option<PathBuf>,
    /// Created if missing; existing report files in it are replaced.
    pub out_dir: PathBuf,
}

/// Episode-return statistics of one file: mean ± population std over its episodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReturnStat {
    pub mean: f64,
    pub std: f64,
    pub episodes: usize,
}

impl ReturnStat {
    /// `None` for an empty list (no file holds zero episodes, but a caller might pass one).
    pub fn of(returns: &[f64]) -> Option<Self> {
        if returns.is_empty() {
            return None;
        }
        let n = returns.len() as f64;
        let mean = returns.iter().sum::<f64>() / n;
        let var = returns.iter().map(|r| (r - mean) * (r - mean)).sum::<f64>() / n;
        Some(Self { mean, std: var.sqrt(), episodes: returns.len() })
    }
}

/// The reference's expert return for one task, and the file it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceReturn {
    /// `expert` or `prompt-expert`.
    pub mode: String,
    pub path: PathBuf,
    pub stat: ReturnStat,
}

/// One task of a family: our modes' returns and the reference's.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskRow {
    pub index: usize,
    /// Aligned with [`FamilyReport::modes`]; `None` where this task has no file of that mode.
    pub modes: Vec<Option<ReturnStat>>,
    pub reference: Option<ReferenceReturn>,
    /// ours expert / reference, only for a positive reference return (a ratio of negative
    /// returns reads backwards).
    pub ratio: Option<f64>,
    /// (ours expert − reference) / |reference|: negative means worse than the reference.
    pub rel_gap: Option<f64>,
    /// Whether this task meets the family's per-task reference bar (Cheetah-Dir, Cheetah-Vel);
    /// `None` where the family has no such bar or either number is missing.
    pub meets_bar: Option<bool>,
}

/// Mean over tasks of the per-task means, and how many tasks it covers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TaskMean {
    pub mean: f64,
    pub tasks: usize,
}

impl TaskMean {
    fn of(values: impl IntoIterator<Item = f64>) -> Option<Self> {
        let v: Vec<f64> = values.into_iter().collect();
        (!v.is_empty())
            .then(|| Self { mean: v.iter().sum::<f64>() / v.len() as f64, tasks: v.len() })
    }
}

/// Outcome of a quality bar.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BarStatus {
    Met,
    NotMet,
    /// The data needed is absent (no reference given, no medium data, ...).
    NotEvaluated,
}

impl BarStatus {
    pub fn label(self) -> &'static str {
        match self {
            BarStatus::Met => "met",
            BarStatus::NotMet => "not met",
            BarStatus::NotEvaluated => "not evaluated",
        }
    }
}

/// One quality bar and its outcome.
#[derive(Debug, Clone, PartialEq)]
pub struct QualityBar {
    /// What the bar requires, e.g. "expert ≥ 90 % of the reference on every task".
    pub name: String,
    pub status: BarStatus,
    /// The numbers behind the outcome, or why it could not be evaluated.
    pub detail: String,
}

/// The report of one environment family.
#[derive(Debug, Clone, PartialEq)]
pub struct FamilyReport {
    pub env: String,
    /// Modes present in our data: `expert`, `medium`, `random`, the `prompt-` ones, then any
    /// other mode alphabetically.
    pub modes: Vec<String>,
    /// The mode that stands for "our expert data": `expert`, else `prompt-expert`.
    pub expert_mode: Option<String>,
    /// In task-index order; every task that our data or the reference has.
    pub tasks: Vec<TaskRow>,
    /// Aligned with `modes`: mean over tasks of each task's mean return.
    pub mode_means: Vec<Option<TaskMean>>,
    pub reference_mean: Option<TaskMean>,
    pub bars: Vec<QualityBar>,
    /// `dataset_returns_<file_stem>.{csv,md,png,svg}`.
    pub file_stem: String,
    /// The content of `dataset_returns_<file_stem>.md`, for printing.
    pub markdown: String,
}

/// What [`dataset_report`] produced.
#[derive(Debug, Clone)]
pub struct DatasetReportSummary {
    /// One per environment family found in `ours`, in natural order of their names.
    pub families: Vec<FamilyReport>,
    /// Every file written, in the order written.
    pub files: Vec<PathBuf>,
    /// Non-fatal problems (a skipped file name, a card that disagrees with its files).
    pub warnings: Vec<String>,
}

/// The standard modes in display order; D_i before P_i, best data first.
const MODE_ORDER: [&str; 6] =
    ["expert", "medium", "random", "prompt-expert", "prompt-medium", "prompt-random"];

/// A per-task bar against the reference: ours expert ≥ ref − tolerance·|ref| on every one of the
/// family's tasks (= ≥ (1 − tolerance) × ref for a positive reference). Better than the
/// reference is always fine.
struct ReferenceBar {
    tolerance: f64,
    tasks: usize,
    name: &'static str,
}

/// A bar on the mean expert return over the family's tasks.
struct MeanBar {
    min: f64,
    tasks: usize,
    name: &'static str,
}

/// The quality bars of the project's issue; task counts are the paper's (Cheetah-Dir 2,
/// Cheetah-Vel 40, Ant-Dir 50), hard-coded because pdt-report must not depend on pdt-envs.
fn reference_bar(env: &str) -> Option<ReferenceBar> {
    match env {
        "cheetah_dir" => Some(ReferenceBar {
            tolerance: 0.10,
            tasks: 2,
            name: "expert ≥ 90 % of the reference's return on every task",
        }),
        "cheetah_vel" => Some(ReferenceBar {
            tolerance: 0.15,
            tasks: 40,
            name: "expert within 15 % of the reference's return (or better) on every task",
        }),
        _ => None,
    }
}

fn mean_bar(env: &str) -> Option<MeanBar> {
    (env == "ant_dir").then_some(MeanBar {
        min: 450.0,
        tasks: 50,
        name: "mean expert return over the tasks ≥ 450 (the paper's target return is 500)",
    })
}

/// Loads `cfg.ours` (and `cfg.reference`), evaluates every family and writes, per family,
/// `dataset_returns_<env>.{csv,md,png,svg}` into `cfg.out_dir`. Nothing is written unless every
/// file was read and every figure rendered.
pub fn dataset_report(cfg: &DatasetReportConfig) -> Result<DatasetReportSummary, ReportError> {
    let mut warnings = Vec::new();
    let ours_files = scan_dir(&cfg.ours, &mut warnings)?;
    if ours_files.is_empty() {
        return Err(ReportError::NoDataFiles { path: cfg.ours.clone() });
    }
    let reference_files = match &cfg.reference {
        Some(dir) => Some(scan_dir(dir, &mut warnings)?),
        None => None,
    };

    // env -> task -> mode -> returns, read from the files themselves.
    let mut ours: BTreeMap<String, BTreeMap<usize, BTreeMap<String, ReturnStat>>> = BTreeMap::new();
    let mut stats_by_path: BTreeMap<PathBuf, ReturnStat> = BTreeMap::new();
    for ((env, index, mode), path) in &ours_files {
        let Some(stat) = ReturnStat::of(&read_returns(path)?) else { continue };
        stats_by_path.insert(path.clone(), stat);
        ours.entry(env.clone()).or_default().entry(*index).or_default().insert(mode.clone(), stat);
    }
    check_card(&cfg.ours, &stats_by_path, &mut warnings);

    let mut envs: Vec<&String> = ours.keys().collect();
    envs.sort_by(|a, b| natural_cmp(a, b));
    let mut stems = BTreeSet::new();
    let mut families = Vec::new();
    for env in envs {
        let reference = match (&cfg.reference, &reference_files) {
            (Some(dir), Some(files)) => {
                let tasks = load_reference(files, env)?;
                if tasks.is_empty() {
                    warnings.push(format!(
                        "{}: no expert or prompt-expert file of {env}; no reference column",
                        dir.display()
                    ));
                    RefData::NoFiles
                } else {
                    RefData::Tasks(tasks)
                }
            }
            _ => RefData::NotGiven,
        };
        let mut family = build_family(env, &ours[env], &reference);
        family.file_stem = file_stem(env, &mut stems);
        families.push(family);
    }
    for family in &mut families {
        family.markdown = family_markdown(family, &cfg.ours, cfg.reference.as_deref(), &warnings);
    }

    // Render everything before writing anything, so a failure leaves out_dir as it was.
    let mut outputs: Vec<(String, Vec<u8>)> = Vec::new();
    for family in &families {
        let stem = format!("dataset_returns_{}", family.file_stem);
        outputs.push((format!("{stem}.csv"), family_csv(family).into_bytes()));
        outputs.push((format!("{stem}.md"), family.markdown.clone().into_bytes()));
        let fig = family_figure(family, &format!("{stem}.png"))?;
        outputs.push((format!("{stem}.png"), fig.png));
        outputs.push((format!("{stem}.svg"), fig.svg.into_bytes()));
    }
    let files = write_outputs(&cfg.out_dir, &outputs)?;
    Ok(DatasetReportSummary { families, files, warnings })
}

// ---------------------------------------------------------------------------------------------
// Reading
// ---------------------------------------------------------------------------------------------

/// (env, task index, mode) of a data file.
type FileKey = (String, usize, String);

/// The data files directly in `dir`, keyed by what they hold. A native file's metadata is
/// authoritative over its name (docs/data-format.md); a pickle has only its name. When two files
/// hold the same (env, task, mode), the `.safetensors` wins, as with the loader's `auto` format.
fn scan_dir(
    dir: &Path,
    warnings: &mut Vec<String>,
) -> Result<BTreeMap<FileKey, PathBuf>, ReportError> {
    let meta = fs::metadata(dir).map_err(|e| ReportError::io(dir, e))?;
    if !meta.is_dir() {
        return Err(ReportError::NotADirectory { path: dir.to_path_buf() });
    }
    let mut paths = Vec::new();
    for entry in fs::read_dir(dir).map_err(|e| ReportError::io(dir, e))? {
        let path = entry.map_err(|e| ReportError::io(dir, e))?.path();
        let ext = path.extension().and_then(|e| e.to_str());
        if matches!(ext, Some("pkl" | "safetensors")) && path.is_file() {
            paths.push(path);
        }
    }
    // Natural order so that warnings and duplicate resolution do not depend on read_dir order.
    paths.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));

    let mut files: BTreeMap<FileKey, PathBuf> = BTreeMap::new();
    for path in paths {
        let Some(key) = file_key(&path, warnings)? else { continue };
        match files.get(&key) {
            None => {
                files.insert(key, path);
            }
            // A converted pickle next to its original is the normal case: the native file
            // wins silently. Two files of the same kind holding the same set is a naming error.
            Some(kept) if is_native(kept) == is_native(&path) => warnings.push(format!(
                "{} and {} both hold {}-{}-{}; using the first",
                kept.display(),
                path.display(),
                key.0,
                key.1,
                key.2
            )),
            Some(_) => {
                if is_native(&path) {
                    files.insert(key, path);
                }
            }
        }
    }
    Ok(files)
}

fn is_native(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()) == Some(FILE_EXTENSION)
}

fn file_key(path: &Path, warnings: &mut Vec<String>) -> Result<Option<FileKey>, ReportError> {
    let from_name = native::FileMeta::from_file_name(path).unwrap_or_default();
    let meta = if is_native(path) {
        native::read_file_meta(path)
            .map_err(|source| ReportError::Data { path: path.to_path_buf(), source })?
    } else {
        native::FileMeta::default()
    };
    let env = meta.env.clone().or_else(|| from_name.env.clone());
    let index = meta.task_index.or(from_name.task_index);
    let mode = meta.mode.clone().or_else(|| from_name.mode.clone());
    let (Some(env), Some(index), Some(mode)) = (env, index, mode) else {
        warnings.push(format!(
            "{}: skipped, neither its name nor its metadata says env, task and mode \
             ({{env}}-{{task}}-{{mode}})",
            path.display()
        ));
        return Ok(None);
    };
    let differs =
        |a: &Option<String>, b: &Option<String>| matches!((a, b), (Some(x), Some(y)) if x != y);
    if differs(&meta.env, &from_name.env)
        || differs(&meta.mode, &from_name.mode)
        || matches!((meta.task_index, from_name.task_index), (Some(x), Some(y)) if x != y)
    {
        warnings.push(format!(
            "{}: its metadata says {env}-{index}-{mode}, its name says otherwise; using the \
             metadata",
            path.display()
        ));
    }
    Ok(Some((env, index, mode)))
}

/// The undiscounted return of every episode in a native file or a reference pickle.
fn read_returns(path: &Path) -> Result<Vec<f64>, ReportError> {
    let data = |source| ReportError::Data { path: path.to_path_buf(), source };
    let dataset: TaskDataset = if path.extension().and_then(|e| e.to_str()) == Some(FILE_EXTENSION)
    {
        native::read_task_dataset(path).map_err(data)?
    } else {
        load_pickle(path, &ReferenceOptions::default()).map_err(data)?.dataset
    };
    Ok(dataset.returns())
}

/// Per task of `env`, the reference's expert return: its `expert` file if there is one, else its
/// `prompt-expert` file (the release ships only prompt sets for the Cheetah families).
fn load_reference(
    files: &BTreeMap<FileKey, PathBuf>,
    env: &str,
) -> Result<BTreeMap<usize, ReferenceReturn>, ReportError> {
    let mut chosen: BTreeMap<usize, (&str, &PathBuf)> = BTreeMap::new();
    for ((e, index, mode), path) in files {
        if e != env {
            continue;
        }
        let better =
            matches!((mode.as_str(), chosen.get(index)), ("expert", _) | ("prompt-expert", None));
        if better {
            chosen.insert(*index, (mode.as_str(), path));
        }
    }
    let mut out = BTreeMap::new();
    for (index, (mode, path)) in chosen {
        if let Some(stat) = ReturnStat::of(&read_returns(path)?) {
            out.insert(index, ReferenceReturn { mode: mode.to_string(), path: path.clone(), stat });
        }
    }
    Ok(out)
}

/// Warns where `dataset.json` disagrees with the files it describes. The card is never used for
/// the numbers; a disagreement means it is stale (files regenerated or edited afterwards).
fn check_card(dir: &Path, stats: &BTreeMap<PathBuf, ReturnStat>, warnings: &mut Vec<String>) {
    let card = match native::read_card(dir) {
        Ok(Some(card)) => card,
        Ok(None) => return,
        Err(e) => {
            warnings.push(format!("{e} (the card is ignored; returns come from the files)"));
            return;
        }
    };
    let card_path = dir.join(native::CARD_FILE_NAME);
    for file in card.tasks.iter().flat_map(|t| &t.files) {
        if let Some((env, _, _)) = native::parse_task_file_stem(
            file.name.strip_suffix(".safetensors").unwrap_or(&file.name),
        ) {
            if env != card.env {
                warnings.push(format!(
                    "{}: says the data are `{}`'s but lists {} (the card is wrong)",
                    card_path.display(),
                    card.env,
                    file.name
                ));
            }
        }
        let path = dir.join(&file.name);
        let Some(s) = stats.get(&path) else { continue };
        let tol = 1e-6 * s.mean.abs().max(1.0);
        if file.episodes != s.episodes || (file.returns.mean - s.mean).abs() > tol {
            warnings.push(format!(
                "{}: says {} has {} episodes with mean return {:.4}, the file has {} with {:.4}; \
                 the card is stale",
                card_path.display(),
                file.name,
                file.episodes,
                file.returns.mean,
                s.episodes,
                s.mean
            ));
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Tables and bars
// ---------------------------------------------------------------------------------------------

/// The reference as seen by one family.
enum RefData {
    /// No reference directory was given.
    NotGiven,
    /// The reference directory has no expert file of this family.
    NoFiles,
    Tasks(BTreeMap<usize, ReferenceReturn>),
}

fn mode_rank(mode: &str) -> (usize, String) {
    let rank = MODE_ORDER.iter().position(|m| *m == mode).unwrap_or(MODE_ORDER.len());
    (rank, mode.to_string())
}

/// The mode standing for a quality level (`expert`, `medium`, `random`): the main dataset if the
/// family has one, else the prompt set.
fn level_mode(modes: &[String], level: &str) -> Option<String> {
    let prompt = format!("prompt-{level}");
    let found = [level, prompt.as_str()].into_iter().find(|m| modes.iter().any(|x| x == m));
    found.map(String::from)
}

fn build_family(
    env: &str,
    ours: &BTreeMap<usize, BTreeMap<String, ReturnStat>>,
    reference: &RefData,
) -> FamilyReport {
    let mut modes: Vec<String> = ours
        .values()
        .flat_map(|m| m.keys().cloned())
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    modes.sort_by_key(|m| mode_rank(m));
    let expert_mode = level_mode(&modes, "expert");
    let ref_tasks = match reference {
        RefData::Tasks(t) => Some(t),
        _ => None,
    };
    let ref_bar = reference_bar(env);

    let indices: BTreeSet<usize> =
        ours.keys().copied().chain(ref_tasks.into_iter().flat_map(|t| t.keys().copied())).collect();
    let tasks: Vec<TaskRow> = indices
        .into_iter()
        .map(|index| {
            let own = ours.get(&index);
            let stat = |mode: &str| own.and_then(|m| m.get(mode)).copied();
            let reference = ref_tasks.and_then(|t| t.get(&index)).cloned();
            let expert = expert_mode.as_deref().and_then(stat).map(|s| s.mean);
            let r = reference.as_ref().map(|r| r.stat.mean);
            let (ratio, rel_gap, meets_bar) = match (expert, r) {
                (Some(e), Some(r)) => (
                    (r > 0.0).then(|| e / r),
                    (r != 0.0).then(|| (e - r) / r.abs()),
                    ref_bar.as_ref().map(|b| e >= r - b.tolerance * r.abs()),
                ),
                _ => (None, None, None),
            };
            TaskRow {
                index,
                modes: modes.iter().map(|m| stat(m)).collect(),
                reference,
                ratio,
                rel_gap,
                meets_bar,
            }
        })
        .collect();

    let mode_means: Vec<Option<TaskMean>> = (0..modes.len())
        .map(|j| TaskMean::of(tasks.iter().filter_map(|t| t.modes[j].map(|s| s.mean))))
        .collect();
    let reference_mean =
        TaskMean::of(tasks.iter().filter_map(|t| t.reference.as_ref().map(|r| r.stat.mean)));

    let mut bars = Vec::new();
    if let Some(bar) = &ref_bar {
        bars.push(evaluate_reference_bar(env, bar, &tasks, expert_mode.as_deref(), reference));
    }
    if let Some(bar) = mean_bar(env) {
        bars.push(evaluate_mean_bar(&bar, &modes, &tasks, expert_mode.as_deref()));
    }
    bars.push(evaluate_medium_bar(&modes, &tasks));

    FamilyReport {
        env: env.to_string(),
        modes,
        expert_mode,
        tasks,
        mode_means,
        reference_mean,
        bars,
        file_stem: String::new(),
        markdown: String::new(),
    }
}

fn evaluate_reference_bar(
    env: &str,
    bar: &ReferenceBar,
    tasks: &[TaskRow],
    expert_mode: Option<&str>,
    reference: &RefData,
) -> QualityBar {
    let not_evaluated = |detail: String| QualityBar {
        name: bar.name.to_string(),
        status: BarStatus::NotEvaluated,
        detail,
    };
    match reference {
        RefData::NotGiven => return not_evaluated("no reference given".to_string()),
        RefData::NoFiles => {
            return not_evaluated(format!("the reference has no expert file of {env}"))
        }
        RefData::Tasks(_) => {}
    }
    let Some(expert_mode) = expert_mode else {
        return not_evaluated("our data has no expert or prompt-expert file".to_string());
    };
    let compared: Vec<&TaskRow> = tasks.iter().filter(|t| t.meets_bar.is_some()).collect();
    let met = compared.iter().filter(|t| t.meets_bar == Some(true)).count();
    let failing: Vec<usize> =
        compared.iter().filter(|t| t.meets_bar == Some(false)).map(|t| t.index).collect();
    let missing: Vec<usize> =
        (0..bar.tasks).filter(|i| !compared.iter().any(|t| t.index == *i)).collect();
    let mut detail = format!(
        "{met} of {} tasks meet it (ours: {expert_mode}; ≥ reference − {:.0} % of |reference|)",
        bar.tasks,
        bar.tolerance * 100.0
    );
    if let Some(worst) = compared
        .iter()
        .filter_map(|t| t.rel_gap.map(|g| (t.index, g)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
    {
        let _ = write!(detail, "; worst gap {} on task {}", percent(worst.1), worst.0);
    }
    if !failing.is_empty() {
        let _ = write!(detail, "; failing: task {}", join_indices(&failing));
    }
    if !missing.is_empty() {
        let _ = write!(
            detail,
            "; no comparison (ours or reference missing) for task {}",
            join_indices(&missing)
        );
    }
    let status = if failing.is_empty() && missing.is_empty() && met > 0 {
        BarStatus::Met
    } else {
        BarStatus::NotMet
    };
    QualityBar { name: bar.name.to_string(), status, detail }
}

fn evaluate_mean_bar(
    bar: &MeanBar,
    modes: &[String],
    tasks: &[TaskRow],
    expert_mode: Option<&str>,
) -> QualityBar {
    let Some(j) = expert_mode.and_then(|m| modes.iter().position(|x| x == m)) else {
        return QualityBar {
            name: bar.name.to_string(),
            status: BarStatus::NotEvaluated,
            detail: "our data has no expert or prompt-expert file".to_string(),
        };
    };
    let present: Vec<(usize, f64)> =
        tasks.iter().filter_map(|t| t.modes[j].map(|s| (t.index, s.mean))).collect();
    let missing: Vec<usize> =
        (0..bar.tasks).filter(|i| !present.iter().any(|(k, _)| k == i)).collect();
    let mean = TaskMean::of(present.iter().map(|p| p.1));
    let mut detail = match mean {
        Some(m) => format!(
            "mean {} return {:.2} over {} of {} tasks (bar {:.0})",
            modes[j], m.mean, m.tasks, bar.tasks, bar.min
        ),
        None => format!("no {} return", modes[j]),
    };
    if !missing.is_empty() {
        let _ = write!(detail, "; missing: task {}", join_indices(&missing));
    }
    let status = match mean {
        Some(m) if m.mean >= bar.min && missing.is_empty() => BarStatus::Met,
        _ => BarStatus::NotMet,
    };
    QualityBar { name: bar.name.to_string(), status, detail }
}

/// mean_random < mean_medium < mean_expert, over the tasks that have all three, so the three
/// means describe the same tasks.
fn evaluate_medium_bar(modes: &[String], tasks: &[TaskRow]) -> QualityBar {
    let name = "medium between random and expert (mean over tasks)".to_string();
    let cols: Vec<Option<(String, usize)>> = ["random", "medium", "expert"]
        .iter()
        .map(|level| {
            level_mode(modes, level)
                .and_then(|m| modes.iter().position(|x| *x == m).map(|j| (m, j)))
        })
        .collect();
    let (Some(r), Some(m), Some(e)) = (&cols[0], &cols[1], &cols[2]) else {
        let absent: Vec<&str> = ["random", "medium", "expert"]
            .iter()
            .zip(&cols)
            .filter(|(_, c)| c.is_none())
            .map(|(l, _)| *l)
            .collect();
        return QualityBar {
            name,
            status: BarStatus::NotEvaluated,
            detail: format!("no {} data", absent.join(" / ")),
        };
    };
    let rows: Vec<[f64; 3]> = tasks
        .iter()
        .filter_map(|t| Some([t.modes[r.1]?.mean, t.modes[m.1]?.mean, t.modes[e.1]?.mean]))
        .collect();
    if rows.is_empty() {
        return QualityBar {
            name,
            status: BarStatus::NotEvaluated,
            detail: format!("no task has all of {}, {}, {}", r.0, m.0, e.0),
        };
    }
    let n = rows.len() as f64;
    let mean_of = |k: usize| rows.iter().map(|row| row[k]).sum::<f64>() / n;
    let (mr, mm, me) = (mean_of(0), mean_of(1), mean_of(2));
    let mut detail = format!(
        "{} {mr:.2} {} {} {mm:.2} {} {} {me:.2} over {} task{}",
        r.0,
        if mr < mm { "<" } else { "≥" },
        m.0,
        if mm < me { "<" } else { "≥" },
        e.0,
        rows.len(),
        if rows.len() == 1 { "" } else { "s" }
    );
    if me > mr {
        // Where medium sits on the random→expert scale (the D4RL-style normalised score).
        let _ = write!(
            detail,
            "; medium at {:.0} % of the way from random to expert",
            100.0 * (mm - mr) / (me - mr)
        );
    }
    let status = if mr < mm && mm < me { BarStatus::Met } else { BarStatus::NotMet };
    QualityBar { name, status, detail }
}

fn join_indices(v: &[usize]) -> String {
    // Long lists (e.g. 38 missing Cheetah-Vel tasks) are shortened into ranges.
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < v.len() {
        let mut j = i;
        while j + 1 < v.len() && v[j + 1] == v[j] + 1 {
            j += 1;
        }
        parts.push(if j > i { format!("{}–{}", v[i], v[j]) } else { v[i].to_string() });
        i = j + 1;
    }
    parts.join(", ")
}

fn percent(x: f64) -> String {
    format!("{:+.1} %", 100.0 * x)
}

fn cell(s: Option<ReturnStat>) -> String {
    match s {
        Some(s) => format!("{:.2} ± {:.2}", s.mean, s.std),
        None => "—".to_string(),
    }
}

/// `dataset_returns_<env>.md`: the table, the means over tasks and the bars. Warnings are
/// appended so the numbers are never read without their caveats.
fn family_markdown(
    f: &FamilyReport,
    ours: &Path,
    reference: Option<&Path>,
    warnings: &[String],
) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "# Dataset returns: {}\n", md(&f.env));
    let _ = writeln!(
        out,
        "Ours: `{}`. Reference: {}.\n",
        ours.display(),
        match reference {
            Some(r) => format!("`{}`", r.display()),
            None => "none given".to_string(),
        }
    );
    let _ = writeln!(
        out,
        "Episode return per task, mean ± std over the file's episodes (population std), \
         recomputed from the data files. `reference`: the reference's `expert` file, else its \
         `prompt-expert` file. Our expert data: `{}`. ratio = ours / reference (only for a \
         positive reference); gap = (ours − reference) / |reference|.\n",
        f.expert_mode.as_deref().unwrap_or("none")
    );
    let has_bar = reference_bar(&f.env).is_some();
    let mut header = vec!["task".to_string()];
    header.extend(f.modes.iter().map(|m| md(m)));
    header.extend(["reference", "ratio", "gap"].map(String::from));
    if has_bar {
        header.push("bar".to_string());
    }
    let _ = writeln!(out, "| {} |", header.join(" | "));
    let _ = writeln!(out, "|{}", " ---: |".repeat(header.len()));
    for t in &f.tasks {
        let mut cells = vec![t.index.to_string()];
        cells.extend(t.modes.iter().map(|s| cell(*s)));
        cells.push(cell(t.reference.as_ref().map(|r| r.stat)));
        cells.push(t.ratio.map_or("—".to_string(), |r| format!("{r:.3}")));
        cells.push(t.rel_gap.map_or("—".to_string(), percent));
        if has_bar {
            cells.push(match t.meets_bar {
                Some(true) => "✓".to_string(),
                Some(false) => "✗".to_string(),
                None => "—".to_string(),
            });
        }
        let _ = writeln!(out, "| {} |", cells.join(" | "));
    }
    let mean_cell = |m: Option<TaskMean>| m.map_or("—".to_string(), |m| format!("{:.2}", m.mean));
    let mut cells = vec!["**mean**".to_string()];
    cells.extend(f.mode_means.iter().map(|m| mean_cell(*m)));
    cells.push(mean_cell(f.reference_mean));
    cells.extend(["", ""].map(String::from));
    if has_bar {
        cells.push(String::new());
    }
    let _ = writeln!(out, "| {} |\n", cells.join(" | "));

    let mut means: Vec<String> = f
        .modes
        .iter()
        .zip(&f.mode_means)
        .filter_map(|(mode, m)| {
            m.map(|m| format!("{} {:.2} ({} tasks)", md(mode), m.mean, m.tasks))
        })
        .collect();
    if let Some(m) = f.reference_mean {
        means.push(format!("reference {:.2} ({} tasks)", m.mean, m.tasks));
    }
    let _ = writeln!(out, "Mean over tasks: {}.\n", means.join("; "));

    let _ = writeln!(out, "## Quality bars\n");
    for b in &f.bars {
        let _ = writeln!(out, "- **{}**: {} — {}.", b.status.label(), b.name, b.detail);
    }
    out.push('\n');
    warnings_markdown(&mut out, warnings);
    out
}

/// `dataset_returns_<env>.csv`: the table at full precision; empty cells where not applicable.
fn family_csv(f: &FamilyReport) -> String {
    let mut header = vec!["task".to_string()];
    for m in &f.modes {
        header.extend([format!("{m}_mean"), format!("{m}_std"), format!("{m}_episodes")]);
    }
    header.extend(
        [
            "reference_mode",
            "reference_mean",
            "reference_std",
            "reference_episodes",
            "ratio",
            "rel_gap",
            "meets_bar",
        ]
        .map(String::from),
    );
    let mut out = csv_line(&header);
    let opt = |v: Option<f64>| v.map(num).unwrap_or_default();
    for t in &f.tasks {
        let mut row = vec![t.index.to_string()];
        for s in &t.modes {
            row.extend([
                opt(s.map(|s| s.mean)),
                opt(s.map(|s| s.std)),
                s.map(|s| s.episodes.to_string()).unwrap_or_default(),
            ]);
        }
        let r = t.reference.as_ref();
        row.extend([
            r.map(|r| r.mode.clone()).unwrap_or_default(),
            opt(r.map(|r| r.stat.mean)),
            opt(r.map(|r| r.stat.std)),
            r.map(|r| r.stat.episodes.to_string()).unwrap_or_default(),
            opt(t.ratio),
            opt(t.rel_gap),
            t.meets_bar.map(|b| b.to_string()).unwrap_or_default(),
        ]);
        out.push_str(&csv_line(&row));
    }
    out
}

/// Return per task: our expert, medium and random data and the reference's expert data, each a
/// line of per-task means with a ± std band over the file's episodes.
fn family_figure(f: &FamilyReport, png_name: &str) -> Result<plot::Figure, ReportError> {
    let mut curves = Vec::new();
    let mut subs = Vec::new();
    for (k, level) in ["expert", "medium", "random"].into_iter().enumerate() {
        let Some(mode) = level_mode(&f.modes, level) else { continue };
        let Some(j) = f.modes.iter().position(|m| *m == mode) else { continue };
        let points: Vec<(f64, f64, f64)> = f
            .tasks
            .iter()
            .filter_map(|t| t.modes[j].map(|s| (t.index as f64, s.mean, s.std)))
            .collect();
        subs.push(format!("ours, {} tasks", points.len()));
        curves.push(Curve { name: mode, color: PALETTE[k], points });
    }
    let ref_points: Vec<(f64, f64, f64)> = f
        .tasks
        .iter()
        .filter_map(|t| t.reference.as_ref().map(|r| (t.index as f64, r.stat.mean, r.stat.std)))
        .collect();
    let mut notes =
        vec!["line: mean over episodes".to_string(), "band: ± std over episodes".to_string()];
    if !ref_points.is_empty() {
        let ref_modes: BTreeSet<&str> =
            f.tasks.iter().filter_map(|t| t.reference.as_ref().map(|r| r.mode.as_str())).collect();
        notes.push(format!("reference: {}", ref_modes.into_iter().collect::<Vec<_>>().join(", ")));
        subs.push(format!("{} tasks", ref_points.len()));
        curves.push(Curve { name: "reference".to_string(), color: PALETTE[3], points: ref_points });
    }
    let labels = Labels {
        caption: format!("{}: episode return per task", f.env),
        x_desc: "Task index".to_string(),
        y_desc: "Episode return".to_string(),
        legend_sub: subs,
        notes,
    };
    plot::render_figure(
        &curves,
        &labels,
        XAxis::Tasks,
        &format!("the dataset returns of {}", f.env),
        png_name,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stat(mean: f64) -> ReturnStat {
        ReturnStat { mean, std: 1.0, episodes: 5 }
    }

    /// `tasks` of (index, [(mode, mean)]).
    fn ours(tasks: &[(usize, &[(&str, f64)])]) -> BTreeMap<usize, BTreeMap<String, ReturnStat>> {
        tasks
            .iter()
            .map(|(i, modes)| (*i, modes.iter().map(|(m, v)| (m.to_string(), stat(*v))).collect()))
            .collect()
    }

    fn reference(tasks: &[(usize, f64)]) -> RefData {
        RefData::Tasks(
            tasks
                .iter()
                .map(|(i, v)| {
                    let r = ReferenceReturn {
                        mode: "prompt-expert".to_string(),
                        path: PathBuf::from(format!("ref-{i}.pkl")),
                        stat: stat(*v),
                    };
                    (*i, r)
                })
                .collect(),
        )
    }

    fn bar<'a>(f: &'a FamilyReport, prefix: &str) -> &'a QualityBar {
        f.bars.iter().find(|b| b.name.starts_with(prefix)).expect("bar present")
    }

    #[test]
    fn return_stat_uses_population_std() {
        let s = ReturnStat::of(&[1.0, 3.0]).expect("non-empty");
        assert_eq!((s.mean, s.std, s.episodes), (2.0, 1.0, 2));
        assert!(ReturnStat::of(&[]).is_none());
    }

    #[test]
    fn cheetah_dir_bar_is_ninety_percent_per_task() {
        let data = ours(&[
            (0, &[("expert", 600.0), ("medium", 300.0), ("random", -100.0)]),
            (1, &[("expert", 1000.0), ("medium", 500.0), ("random", -90.0)]),
        ]);
        // 600 ≥ 0.9·660 = 594, 1000 < 0.9·1134 = 1020.6
        let f = build_family("cheetah_dir", &data, &reference(&[(0, 660.0), (1, 1134.0)]));
        assert_eq!(f.modes, ["expert", "medium", "random"]);
        assert_eq!(f.tasks[0].meets_bar, Some(true));
        assert_eq!(f.tasks[1].meets_bar, Some(false));
        assert!((f.tasks[0].ratio.expect("positive ref") - 600.0 / 660.0).abs() < 1e-12);
        let b = bar(&f, "expert ≥ 90 %");
        assert_eq!(b.status, BarStatus::NotMet);
        assert!(
            b.detail.contains("1 of 2 tasks") && b.detail.contains("failing: task 1"),
            "{}",
            b.detail
        );
        assert_eq!(bar(&f, "medium between").status, BarStatus::Met);

        let good = ours(&[(0, &[("expert", 600.0)]), (1, &[("expert", 1100.0)])]);
        let f = build_family("cheetah_dir", &good, &reference(&[(0, 660.0), (1, 1134.0)]));
        assert_eq!(bar(&f, "expert ≥ 90 %").status, BarStatus::Met);
        // No medium / random data: that bar cannot be evaluated.
        let m = bar(&f, "medium between");
        assert_eq!(m.status, BarStatus::NotEvaluated);
        assert!(m.detail.contains("no random / medium data"), "{}", m.detail);
    }

    #[test]
    fn cheetah_vel_bar_allows_fifteen_percent_below_a_negative_reference() {
        // Reference −20: the bar is −23. −22.9 passes, −23.1 fails, −5 (better) passes.
        let data =
            ours(&[(0, &[("expert", -22.9)]), (1, &[("expert", -23.1)]), (2, &[("expert", -5.0)])]);
        let f =
            build_family("cheetah_vel", &data, &reference(&[(0, -20.0), (1, -20.0), (2, -20.0)]));
        let got: Vec<Option<bool>> = f.tasks.iter().map(|t| t.meets_bar).collect();
        assert_eq!(got, [Some(true), Some(false), Some(true)]);
        // A ratio of negative returns reads backwards, so none is given; the gap is.
        assert!(f.tasks.iter().all(|t| t.ratio.is_none()));
        assert!((f.tasks[0].rel_gap.expect("gap") + 0.145).abs() < 1e-9);
        let b = bar(&f, "expert within 15 %");
        assert_eq!(b.status, BarStatus::NotMet);
        assert!(b.detail.contains("2 of 40 tasks meet it"), "{}", b.detail);
        assert!(b.detail.contains("missing) for task 3–39"), "{}", b.detail);

        let all: Vec<(usize, f64)> = (0..40).map(|i| (i, -20.0 - i as f64)).collect();
        let data: BTreeMap<usize, BTreeMap<String, ReturnStat>> = all
            .iter()
            .map(|(i, r)| (*i, [("expert".to_string(), stat(r * 1.1))].into_iter().collect()))
            .collect();
        let f = build_family("cheetah_vel", &data, &reference(&all));
        assert_eq!(bar(&f, "expert within 15 %").status, BarStatus::Met);
        assert_eq!(f.reference_mean.expect("ref").tasks, 40);
    }

    #[test]
    fn reference_bar_without_reference_is_not_evaluated() {
        let data = ours(&[(0, &[("expert", 600.0)])]);
        let f = build_family("cheetah_dir", &data, &RefData::NotGiven);
        assert_eq!(bar(&f, "expert ≥ 90 %").status, BarStatus::NotEvaluated);
        assert!(f.tasks[0].reference.is_none() && f.tasks[0].meets_bar.is_none());
        let f = build_family("cheetah_dir", &data, &RefData::NoFiles);
        assert_eq!(bar(&f, "expert ≥ 90 %").status, BarStatus::NotEvaluated);
    }

    #[test]
    fn ant_dir_bar_is_on_the_mean_over_fifty_tasks() {
        let mk = |n: usize, v: f64| -> BTreeMap<usize, BTreeMap<String, ReturnStat>> {
            (0..n).map(|i| (i, [("expert".to_string(), stat(v))].into_iter().collect())).collect()
        };
        let f = build_family("ant_dir", &mk(50, 460.0), &RefData::NotGiven);
        assert_eq!(bar(&f, "mean expert return").status, BarStatus::Met);
        let f = build_family("ant_dir", &mk(50, 440.0), &RefData::NotGiven);
        assert_eq!(bar(&f, "mean expert return").status, BarStatus::NotMet);
        let f = build_family("ant_dir", &mk(10, 600.0), &RefData::NotGiven);
        let b = bar(&f, "mean expert return");
        assert_eq!(b.status, BarStatus::NotMet);
        assert!(
            b.detail.contains("10 of 50 tasks") && b.detail.contains("missing: task 10–49"),
            "{}",
            b.detail
        );
    }

    #[test]
    fn medium_bar_uses_tasks_with_all_three_and_falls_back_to_prompt_sets() {
        let data = ours(&[
            (0, &[("prompt-expert", 10.0), ("prompt-medium", 12.0), ("prompt-random", 1.0)]),
            (1, &[("prompt-expert", 10.0), ("prompt-medium", 5.0), ("prompt-random", 1.0)]),
        ]);
        let f = build_family("point_robot", &data, &RefData::NotGiven);
        assert_eq!(f.expert_mode.as_deref(), Some("prompt-expert"));
        // Means: random 1 < medium 8.5 < expert 10.
        let b = bar(&f, "medium between");
        assert_eq!(b.status, BarStatus::Met, "{}", b.detail);
        assert!(b.detail.contains("over 2 tasks") && b.detail.contains("83 %"), "{}", b.detail);
        // point_robot has no family bar: the medium bar is the only one.
        assert_eq!(f.bars.len(), 1);

        let data = ours(&[(0, &[("expert", 10.0), ("medium", 12.0), ("random", 1.0)])]);
        let f = build_family("point_robot", &data, &RefData::NotGiven);
        let b = bar(&f, "medium between");
        assert_eq!(b.status, BarStatus::NotMet);
        assert!(b.detail.contains("medium 12.00 ≥ expert 10.00"), "{}", b.detail);
    }

    #[test]
    fn modes_are_ordered_and_tables_cover_reference_only_tasks() {
        let data =
            ours(&[(1, &[("random", 1.0), ("zzz", 3.0), ("prompt-expert", 2.0), ("expert", 4.0)])]);
        let mut f = build_family("cheetah_dir", &data, &reference(&[(0, 5.0), (1, 4.0)]));
        assert_eq!(f.modes, ["expert", "random", "prompt-expert", "zzz"]);
        assert_eq!(f.tasks.iter().map(|t| t.index).collect::<Vec<_>>(), [0, 1]);
        assert!(f.tasks[0].modes.iter().all(Option::is_none));
        f.file_stem = "cheetah_dir".to_string();
        let md = family_markdown(&f, Path::new("/d"), Some(Path::new("/r")), &["w1".to_string()]);
        assert!(
            md.contains(
                "| task | expert | random | prompt-expert | zzz | reference | ratio | gap | bar |"
            ),
            "{md}"
        );
        assert!(md.contains("| 1 | 4.00 ± 1.00 | 1.00 ± 1.00 | 2.00 ± 1.00 | 3.00 ± 1.00 | 4.00 ± 1.00 | 1.000 | +0.0 % | ✓ |"), "{md}");
        assert!(md.contains("| 0 | — | — | — | — | 5.00 ± 1.00 | — | — | — |"), "{md}");
        assert!(md.contains("- **not met**: expert ≥ 90 %"), "{md}");
        assert!(md.contains("## Warnings\n\n- w1"), "{md}");
        let csv = family_csv(&f);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines[0], "task,expert_mean,expert_std,expert_episodes,random_mean,random_std,random_episodes,prompt-expert_mean,prompt-expert_std,prompt-expert_episodes,zzz_mean,zzz_std,zzz_episodes,reference_mode,reference_mean,reference_std,reference_episodes,ratio,rel_gap,meets_bar");
        assert_eq!(lines[1], "0,,,,,,,,,,,,,prompt-expert,5,1,5,,,");
        assert_eq!(lines[2], "1,4,1,5,1,1,5,2,1,5,3,1,5,prompt-expert,4,1,5,1,0,true");
    }

    #[test]
    fn index_lists_become_ranges() {
        assert_eq!(join_indices(&[0, 1, 2, 5, 7, 8]), "0–2, 5, 7–8");
        assert_eq!(join_indices(&[]), "");
    }
}
