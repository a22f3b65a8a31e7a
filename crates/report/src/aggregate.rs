//! Turns loaded runs into the numbers the report shows: per-seed final values and learning
//! curves, then mean and standard deviation over the seeds of each (environment, method).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::PathBuf;

use crate::error::ReportError;
use crate::load::Run;
use pdt_rundir::config::Method;

/// Methods in the order the paper lists them ([`Method::ALL`]); they also fix each method's plot
/// colour, so a method has the same colour in every environment's figure.
pub(crate) const METHOD_ORDER: [Method; Method::ALL.len()] = Method::ALL;

/// Sort key for methods: known methods in paper order, then the rest alphabetically.
pub(crate) fn method_rank(method: &str) -> (usize, String) {
    let idx = METHOD_ORDER.iter().position(|m| m.name() == method).unwrap_or(METHOD_ORDER.len());
    (idx, method.to_string())
}

/// Mean and standard deviation over seeds.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Stat {
    pub mean: f64,
    /// Population standard deviation (divides by n, numpy's default), so one seed gives 0.
    pub std: f64,
    pub n: usize,
}

impl Stat {
    /// Statistics of the finite values. A non-finite value (a diverged seed's NaN return) is
    /// left out rather than turning the whole cell into NaN; `n` counts only what was used, so
    /// the cell shows "(n=k)" and a warning says which run it was. `None` when nothing is left:
    /// a cell nobody measured has no value, not 0.
    pub fn of(values: &[f64]) -> Option<Stat> {
        let finite: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
        if finite.is_empty() {
            return None;
        }
        let n = finite.len() as f64;
        let mean = finite.iter().sum::<f64>() / n;
        let var = finite.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
        Some(Stat { mean, std: var.sqrt(), n: finite.len() })
    }
}

/// Where a seed's final values came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum FinalSource {
    EvalFinal,
    EvalJsonl,
}

impl FinalSource {
    pub fn as_str(self) -> &'static str {
        match self {
            FinalSource::EvalFinal => "eval_final.json",
            FinalSource::EvalJsonl => "eval.jsonl",
        }
    }
}

/// The numbers of one run (= one seed) that enter the report.
#[derive(Debug, Clone)]
struct SeedData {
    run: usize,
    final_tasks: BTreeMap<String, f64>,
    final_average: f64,
    final_iteration: Option<u64>,
    source: FinalSource,
    /// (iteration, average test return) for every evaluation that covered all test tasks.
    curve: Vec<(u64, f64)>,
}

/// One row of an environment's table.
#[derive(Debug, Clone)]
pub struct MethodRow {
    pub method: String,
    pub n_seeds: usize,
    /// Aligned with `EnvReport::tasks`; `None` where no seed of this method has that task.
    pub tasks: Vec<Option<Stat>>,
    /// `None` only if every seed's average is non-finite.
    pub average: Option<Stat>,
    /// Smallest and largest iteration the seeds' final values come from, when known.
    pub iterations: Option<(u64, u64)>,
}

#[derive(Debug, Clone)]
pub struct CurvePoint {
    pub iteration: u64,
    pub stat: Stat,
}

#[derive(Debug, Clone)]
pub struct MethodCurve {
    pub method: String,
    pub n_seeds: usize,
    pub points: Vec<CurvePoint>,
}

/// Everything reported for one environment (and split).
#[derive(Debug, Clone)]
pub struct EnvReport {
    /// `env`, or `env (split)` for a non-default split.
    pub env: String,
    /// File-name-safe and unique among environments; used in `curves_<stem>.png`.
    pub file_stem: String,
    /// Test tasks in task-index order.
    pub tasks: Vec<String>,
    pub rows: Vec<MethodRow>,
    /// Methods with at least one curve point, in the same order as `rows`.
    pub curves: Vec<MethodCurve>,
}

/// One line of `runs.csv`.
#[derive(Debug, Clone)]
pub struct RunSummary {
    pub dir: PathBuf,
    pub name: String,
    pub env: String,
    pub split: String,
    pub method: String,
    pub seed: Option<u64>,
    /// `None` when the run was left out (no test evaluation).
    pub final_source: Option<&'static str>,
    pub final_iteration: Option<u64>,
    pub final_average: Option<f64>,
    pub n_test_tasks: usize,
    pub n_curve_points: usize,
    pub last_train_iteration: Option<u64>,
    /// The `metrics.jsonl` column holding the run's loss (its method's: `RunInfo::loss_metric`).
    pub loss_metric: String,
    /// That column in the last metrics line.
    pub last_loss: Option<f64>,
    pub elapsed_s: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct Aggregated {
    pub envs: Vec<EnvReport>,
    pub runs: Vec<RunSummary>,
    pub runs_used: usize,
    pub runs_skipped: usize,
    /// Runs with offline evaluations only (action errors, `crate::offline`): in no returns table.
    pub offline_only: usize,
}

/// Computes the whole report. Problems that do not stop the report (runs without test
/// evaluations, partial evaluations, mismatched task sets) are appended to `warnings`.
pub(crate) fn aggregate(
    runs: &[Run],
    warnings: &mut Vec<String>,
) -> Result<Aggregated, ReportError> {
    let mut task_index: HashMap<String, i64> = HashMap::new();
    let mut seeds: Vec<Option<SeedData>> = Vec::with_capacity(runs.len());
    let mut missing = Vec::new();
    let mut offline_only = 0;
    for (i, run) in runs.iter().enumerate() {
        collect_task_indices(run, &mut task_index);
        match seed_data(i, run, warnings) {
            Ok(s) => seeds.push(Some(s)),
            // Evaluated offline only (no environment): reported in the action-error table
            // (`crate::offline`), not left out.
            Err(_) if run.offline_evals.is_some() || run.offline_final.is_some() => {
                offline_only += 1;
                seeds.push(None);
            }
            Err(why) => {
                warnings.push(format!("{why}; run left out of the table and curves"));
                missing.push(why);
                seeds.push(None);
            }
        }
    }
    let runs_used = seeds.iter().filter(|s| s.is_some()).count();
    if runs_used + offline_only == 0 {
        return Err(ReportError::NoEvalData { details: missing });
    }

    // env label -> method -> seeds
    let mut groups: BTreeMap<String, BTreeMap<(usize, String), Vec<&SeedData>>> = BTreeMap::new();
    for s in seeds.iter().flatten() {
        let run = &runs[s.run];
        groups
            .entry(run.env_label())
            .or_default()
            .entry(method_rank(&run.info.method))
            .or_default()
            .push(s);
    }

    let mut envs = Vec::new();
    let mut stems = BTreeSet::new();
    for (env, methods) in &groups {
        envs.push(env_report(env, methods, runs, &task_index, &mut stems, warnings));
    }

    let run_summaries =
        runs.iter().zip(&seeds).map(|(run, s)| run_summary(run, s.as_ref())).collect();
    let runs_skipped = runs.len() - runs_used - offline_only;
    Ok(Aggregated { envs, runs: run_summaries, runs_used, runs_skipped, offline_only })
}

fn collect_task_indices(run: &Run, out: &mut HashMap<String, i64>) {
    let from_evals = run.evals.iter().flatten().map(|e| (&e.task, e.task_index));
    let from_final = run.final_eval.iter().flat_map(|f| &f.tasks).map(|t| (&t.task, t.task_index));
    for (task, idx) in from_evals.chain(from_final) {
        out.entry(task.clone()).or_insert(idx as i64);
    }
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        sum / n as f64
    }
}

/// Extracts one seed's final values and curve, or says why the run has none.
fn seed_data(i: usize, run: &Run, warnings: &mut Vec<String>) -> Result<SeedData, String> {
    let dir = run.dir.display();
    // iteration -> task -> return; a later line for the same (iteration, task) wins, as the
    // latest write is the one a resumed run stands by.
    let mut by_iter: BTreeMap<u64, BTreeMap<String, f64>> = BTreeMap::new();
    for e in run.evals.iter().flatten().filter(|e| e.is_test()) {
        by_iter.entry(e.iteration).or_default().insert(e.task.clone(), e.return_mean);
    }
    let all_tasks: BTreeSet<&String> = by_iter.values().flat_map(|m| m.keys()).collect();
    // An evaluation that does not cover every test task (e.g. the run was killed mid-evaluation)
    // would give an average over different tasks than its neighbours, so it is left out.
    let partial: Vec<u64> =
        by_iter.iter().filter(|(_, m)| m.len() < all_tasks.len()).map(|(it, _)| *it).collect();
    if !partial.is_empty() {
        warnings.push(format!(
            "{dir}/eval.jsonl: the evaluation(s) at iteration(s) {} cover fewer than all {} test tasks; left out of the learning curve",
            join_u64(&partial),
            all_tasks.len()
        ));
    }
    let curve: Vec<(u64, f64)> = by_iter
        .iter()
        .filter(|(_, m)| m.len() == all_tasks.len())
        .map(|(it, m)| (*it, mean(m.values().copied())))
        .collect();

    let non_finite: Vec<String> = by_iter
        .iter()
        .flat_map(|(it, m)| {
            m.iter().filter(|(_, v)| !v.is_finite()).map(move |(t, _)| format!("{t}@{it}"))
        })
        .collect();
    if !non_finite.is_empty() {
        warnings.push(format!(
            "{dir}/eval.jsonl: non-finite return (null/NaN) for {}; those evaluations are left out of the means",
            non_finite.join(", ")
        ));
    }

    let mut final_note = "missing";
    if let Some(fe) = &run.final_eval {
        if fe.eval_on != "test" {
            final_note = "not on the test split";
            warnings.push(format!(
                "{dir}/eval_final.json: evaluated on {:?}, not \"test\"; using eval.jsonl instead",
                fe.eval_on
            ));
        } else if fe.tasks.is_empty() {
            final_note = "has no tasks";
            warnings.push(format!("{dir}/eval_final.json: has no tasks; using eval.jsonl instead"));
        } else {
            let final_tasks: BTreeMap<String, f64> =
                fe.tasks.iter().map(|t| (t.task.clone(), t.return_mean)).collect();
            let bad: Vec<&str> = fe
                .tasks
                .iter()
                .filter(|t| !t.return_mean.is_finite())
                .map(|t| t.task.as_str())
                .collect();
            if !bad.is_empty() {
                warnings.push(format!(
                    "{dir}/eval_final.json: non-finite return (null/NaN) for {}; left out of the means",
                    bad.join(", ")
                ));
            }
            return Ok(SeedData {
                run: i,
                final_average: mean(final_tasks.values().copied()),
                final_tasks,
                final_iteration: Some(fe.iteration),
                source: FinalSource::EvalFinal,
                curve,
            });
        }
    }

    if let Some((it, m)) = by_iter.iter().rev().find(|(_, m)| m.len() == all_tasks.len()) {
        return Ok(SeedData {
            run: i,
            final_tasks: m.clone(),
            final_average: mean(m.values().copied()),
            final_iteration: Some(*it),
            source: FinalSource::EvalJsonl,
            curve,
        });
    }
    if !by_iter.is_empty() {
        // No single evaluation covered every task: fall back to each task's latest value.
        let mut latest: BTreeMap<String, f64> = BTreeMap::new();
        for m in by_iter.values() {
            for (t, v) in m {
                latest.insert(t.clone(), *v);
            }
        }
        warnings.push(format!(
            "{dir}/eval.jsonl: no evaluation covers all test tasks; final values are each task's latest evaluation"
        ));
        return Ok(SeedData {
            run: i,
            final_average: mean(latest.values().copied()),
            final_tasks: latest,
            final_iteration: by_iter.keys().next_back().copied(),
            source: FinalSource::EvalJsonl,
            curve,
        });
    }

    let evals_note = match &run.evals {
        None => "missing",
        Some(_) => "has no lines with split \"test\"",
    };
    Err(format!(
        "{dir}: no test evaluation found (eval_final.json {final_note}; eval.jsonl {evals_note})"
    ))
}

fn join_u64(v: &[u64]) -> String {
    v.iter().map(|x| x.to_string()).collect::<Vec<_>>().join(", ")
}

pub(crate) fn file_stem(env: &str, used: &mut BTreeSet<String>) -> String {
    let mut base: String =
        env.chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
                    c
                } else {
                    '_'
                }
            })
            .collect();
    // "env (ood)" -> "env__ood_" -> "env_ood": tidy separators produced by the mapping.
    while base.contains("__") {
        base = base.replace("__", "_");
    }
    let base = base.trim_matches('_').to_string();
    let base = if base.is_empty() { "env".to_string() } else { base };
    let mut stem = base.clone();
    let mut k = 2;
    while !used.insert(stem.clone()) {
        stem = format!("{base}-{k}");
        k += 1;
    }
    stem
}

fn env_report(
    env: &str,
    methods: &BTreeMap<(usize, String), Vec<&SeedData>>,
    runs: &[Run],
    task_index: &HashMap<String, i64>,
    stems: &mut BTreeSet<String>,
    warnings: &mut Vec<String>,
) -> EnvReport {
    let mut task_set: BTreeSet<&String> = BTreeSet::new();
    for seeds in methods.values() {
        for s in seeds {
            task_set.extend(s.final_tasks.keys());
        }
    }
    let mut tasks: Vec<String> = task_set.into_iter().cloned().collect();
    // Task-index order, like the paper's task lists; unindexed tasks go last, by name.
    tasks.sort_by(|a, b| {
        let ka = (task_index.get(a).copied().unwrap_or(i64::MAX), a);
        let kb = (task_index.get(b).copied().unwrap_or(i64::MAX), b);
        ka.cmp(&kb)
    });

    let mut rows = Vec::new();
    let mut curves = Vec::new();
    for ((_, method), seeds) in methods {
        check_seeds(env, method, seeds, runs, &tasks, warnings);
        let cells = tasks
            .iter()
            .map(|t| {
                let vals: Vec<f64> =
                    seeds.iter().filter_map(|s| s.final_tasks.get(t).copied()).collect();
                Stat::of(&vals)
            })
            .collect();
        let averages: Vec<f64> = seeds.iter().map(|s| s.final_average).collect();
        let iters: Vec<u64> = seeds.iter().filter_map(|s| s.final_iteration).collect();
        let iterations = match (iters.iter().min(), iters.iter().max()) {
            (Some(a), Some(b)) => Some((*a, *b)),
            _ => None,
        };
        rows.push(MethodRow {
            method: method.clone(),
            n_seeds: seeds.len(),
            tasks: cells,
            average: Stat::of(&averages),
            iterations,
        });

        let mut by_iter: BTreeMap<u64, Vec<f64>> = BTreeMap::new();
        for s in seeds {
            for (it, v) in &s.curve {
                by_iter.entry(*it).or_default().push(*v);
            }
        }
        let points: Vec<CurvePoint> = by_iter
            .iter()
            .filter_map(|(it, vals)| Stat::of(vals).map(|stat| CurvePoint { iteration: *it, stat }))
            .collect();
        if !points.is_empty() {
            curves.push(MethodCurve { method: method.clone(), n_seeds: seeds.len(), points });
        }
    }
    if curves.is_empty() {
        warnings.push(format!(
            "{env}: no evaluations during training (eval.jsonl) for any method; no learning-curve plot"
        ));
    }
    EnvReport { env: env.to_string(), file_stem: file_stem(env, stems), tasks, rows, curves }
}

/// Warns about things that make a group's mean ± std questionable.
fn check_seeds(
    env: &str,
    method: &str,
    seeds: &[&SeedData],
    runs: &[Run],
    env_tasks: &[String],
    warnings: &mut Vec<String>,
) {
    let mut by_seed: BTreeMap<u64, Vec<String>> = BTreeMap::new();
    for s in seeds {
        let seed = runs[s.run].info.seed;
        by_seed.entry(seed).or_default().push(runs[s.run].dir.display().to_string());
    }
    for (seed, dirs) in by_seed.iter().filter(|(_, d)| d.len() > 1) {
        warnings.push(format!(
            "{env} / {method}: seed {seed} appears in {} runs ({}); each counts as a separate seed",
            dirs.len(),
            dirs.join(", ")
        ));
    }
    let differing = seeds.iter().filter(|s| s.final_tasks.len() != env_tasks.len()).count();
    if differing > 0 {
        warnings.push(format!(
            "{env} / {method}: {differing} of {} seed(s) were evaluated on fewer than the {} test tasks seen in this environment; their averages are over different task sets",
            seeds.len(),
            env_tasks.len()
        ));
    }
}

fn run_summary(run: &Run, s: Option<&SeedData>) -> RunSummary {
    let last_metrics = run.metrics.as_ref().and_then(|m| m.last());
    RunSummary {
        dir: run.dir.clone(),
        name: if run.info.name.is_empty() {
            run.dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
        } else {
            run.info.name.clone()
        },
        env: run.info.env.clone(),
        split: run.info.task_split.clone(),
        method: run.info.method.clone(),
        seed: Some(run.info.seed),
        final_source: s.map(|s| s.source.as_str()),
        final_iteration: s.and_then(|s| s.final_iteration),
        final_average: s.map(|s| s.final_average),
        n_test_tasks: s.map_or(0, |s| s.final_tasks.len()),
        n_curve_points: s.map_or(0, |s| s.curve.len()),
        last_train_iteration: last_metrics.map(|m| m.iteration),
        loss_metric: run.info.loss_metric().to_string(),
        last_loss: last_metrics.and_then(|m| m.get(run.info.loss_metric())),
        elapsed_s: last_metrics.map(|m| m.elapsed_s),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stat_is_population_std() {
        let s = Stat::of(&[1.0, 2.0, 3.0]);
        assert_eq!(s, Some(Stat { mean: 2.0, std: (2.0f64 / 3.0).sqrt(), n: 3 }));
        assert_eq!(Stat::of(&[5.0]).map(|s| s.std), Some(0.0));
        assert_eq!(Stat::of(&[1.0, f64::NAN, 3.0]).map(|s| (s.mean, s.n)), Some((2.0, 2)));
        assert!(Stat::of(&[f64::NAN]).is_none());
        assert!(Stat::of(&[]).is_none());
    }

    #[test]
    fn stems_are_safe_and_unique() {
        let mut used = BTreeSet::new();
        assert_eq!(file_stem("ant_dir (ood)", &mut used), "ant_dir_ood");
        assert_eq!(file_stem("ant_dir/ood", &mut used), "ant_dir_ood-2");
        assert_eq!(file_stem("???", &mut used), "env");
    }

    #[test]
    fn known_methods_sort_in_paper_order() {
        let mut m = vec!["zzz", "mt-orl", "prompt-dt", "aaa", "macaw"];
        m.sort_by_key(|x| method_rank(x));
        assert_eq!(m, vec!["prompt-dt", "mt-orl", "macaw", "aaa", "zzz"]);
    }
}
