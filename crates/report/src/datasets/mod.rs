//! Dataset-quality report: the episode returns of a dataset directory written by
//! `promptdt collect`, per environment family and task, against the reference release's expert
//! returns, with the project's quality bars evaluated.
//!
//! Returns are always recomputed from the data files; `dataset.json` (the card) is only
//! cross-checked, so a stale or hand-edited card cannot make a dataset look better than it is.
//! How the numbers are computed and which bars apply is documented in `docs/report.md`
//! ("Dataset quality report").

mod bars;
mod card;
mod family;
mod output;
mod read;

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;

use pdt_data::inspect::natural_cmp;

use crate::aggregate::file_stem;
use crate::error::ReportError;
use crate::write_outputs;

use card::check_card;
use family::build_family;
use output::{family_csv, family_figure, family_markdown};
use read::{load_reference, read_returns, scan_dir};

/// The reference as seen by one family.
enum RefData {
    /// No reference directory was given.
    NotGiven,
    /// The reference directory has no expert file of this family.
    NoFiles,
    Tasks(BTreeMap<usize, ReferenceReturn>),
}

/// The mode standing for a quality level (`expert`, `medium`, `random`): the main dataset if the
/// family has one, else the prompt set.
fn level_mode(modes: &[String], level: &str) -> Option<String> {
    let prompt = format!("prompt-{level}");
    let found = [level, prompt.as_str()].into_iter().find(|m| modes.iter().any(|x| x == m));
    found.map(String::from)
}

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
    /// Fraction of the episodes that solved their task at some step, for families whose success
    /// shows in the rewards (Meta-World reach: a reward of 10); `None` for the others.
    pub success: Option<f64>,
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
        Some(Self { mean, std: var.sqrt(), episodes: returns.len(), success: None })
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
        let (returns, success) = read_returns(path, env)?;
        let Some(mut stat) = ReturnStat::of(&returns) else { continue };
        stat.success = success;
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
#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::bars::join_indices;
    use super::*;

    fn stat(mean: f64) -> ReturnStat {
        ReturnStat { mean, std: 1.0, episodes: 5, success: None }
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
