//! The offline evaluations' table: the held-out action error of runs with no environment (a task
//! suite without `[environment]`, `pdt_rundir::offline`), in a table and CSV of their own,
//! labelled as an action error (lower is better), never beside or among returns.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use pdt_base::table::{Rule, Table};

use crate::aggregate::{method_rank, Stat};
use crate::load::Run;
use crate::render::{csv_line, md, num, task_cells};

/// One environment's action errors: rows are methods, columns the held-out tasks.
#[derive(Debug, Clone)]
pub(crate) struct OfflineEnv {
    pub env: String,
    /// Held-out tasks in task-index order.
    pub tasks: Vec<String>,
    pub rows: Vec<OfflineRow>,
}

#[derive(Debug, Clone)]
pub(crate) struct OfflineRow {
    pub method: String,
    pub n_seeds: usize,
    /// Aligned with `OfflineEnv::tasks`.
    pub tasks: Vec<Option<Stat>>,
    pub average: Option<Stat>,
    /// Smallest and largest iteration of the seeds' values.
    pub iterations: (u64, u64),
}

/// One seed's final action errors: `eval_offline.json` on the test tasks if present, else the
/// last offline evaluation in `offline_eval.jsonl` that covers every test task it ever had.
/// `(iteration, task -> (index, error))`.
type SeedErrors = (u64, BTreeMap<String, (usize, f64)>);

fn seed_errors(run: &Run) -> Option<SeedErrors> {
    if let Some(f) =
        run.offline_final.as_ref().filter(|f| f.eval_on == "test" && !f.tasks.is_empty())
    {
        let tasks = f.tasks.iter().map(|t| (t.task.clone(), (t.task_index, t.action_mse)));
        return Some((f.iteration, tasks.collect()));
    }
    let mut by_iter: BTreeMap<u64, BTreeMap<String, (usize, f64)>> = BTreeMap::new();
    for l in run.offline_evals.iter().flatten().filter(|l| l.is_test()) {
        let r = &l.result;
        by_iter
            .entry(l.iteration)
            .or_default()
            .insert(r.task.clone(), (r.task_index, r.action_mse));
    }
    let all = by_iter.values().flat_map(|m| m.keys()).collect::<std::collections::BTreeSet<_>>();
    let n = all.len();
    by_iter.into_iter().rev().find(|(_, m)| m.len() == n)
}

/// The action-error tables of the runs that have offline evaluations, by environment (label as
/// the returns' tables have it) and method in the paper's order.
pub(crate) fn aggregate(runs: &[Run]) -> Vec<OfflineEnv> {
    // env -> method -> seeds' errors
    let mut groups: BTreeMap<String, BTreeMap<(usize, String), Vec<SeedErrors>>> = BTreeMap::new();
    for run in runs {
        if let Some(e) = seed_errors(run) {
            let env = groups.entry(run.env_label()).or_default();
            env.entry(method_rank(&run.info.method)).or_default().push(e);
        }
    }
    groups
        .into_iter()
        .map(|(env, methods)| {
            let mut tasks: Vec<(usize, String)> = methods
                .values()
                .flatten()
                .flat_map(|(_, m)| m.iter().map(|(t, (i, _))| (*i, t.clone())))
                .collect();
            tasks.sort();
            tasks.dedup();
            let rows = methods
                .into_iter()
                .map(|((_, method), seeds)| {
                    let per_task = tasks
                        .iter()
                        .map(|(_, t)| {
                            let v: Vec<f64> =
                                seeds.iter().filter_map(|(_, m)| m.get(t).map(|x| x.1)).collect();
                            Stat::of(&v)
                        })
                        .collect();
                    let averages: Vec<f64> = seeds
                        .iter()
                        .map(|(_, m)| m.values().map(|x| x.1).sum::<f64>() / m.len().max(1) as f64)
                        .collect();
                    let its = seeds.iter().map(|(i, _)| *i);
                    let iterations = (its.clone().min().unwrap_or(0), its.max().unwrap_or(0));
                    OfflineRow {
                        method,
                        n_seeds: seeds.len(),
                        tasks: per_task,
                        average: Stat::of(&averages),
                        iterations,
                    }
                })
                .collect();
            OfflineEnv { env, tasks: tasks.into_iter().map(|(_, t)| t).collect(), rows }
        })
        .collect()
}

/// The Markdown section of the action-error tables (nothing when there are none).
pub(crate) fn markdown(envs: &[OfflineEnv]) -> String {
    let mut out = String::new();
    if envs.is_empty() {
        return out;
    }
    let _ = writeln!(
        out,
        "## Held-out action error (offline evaluation: lower is better, not a return)\n\n\
         Runs with no environment to act in (a task suite without `[environment]`) are evaluated \
         on their held-out tasks' data: the mean squared error of the prompted model's actions \
         against the data's (`offline_eval.jsonl`, `eval_offline.json`; docs/report.md). Mean ± \
         std over seeds (population std); a seed's value is from `eval_offline.json` if present, \
         else its last complete offline evaluation; (n=k): only k seeds contribute. These \
         numbers are not returns and are not normalised.\n"
    );
    for env in envs {
        let _ = writeln!(out, "### {}: action MSE\n", md(&env.env));
        let mut header = vec!["method".to_string(), "seeds".to_string(), "iteration".to_string()];
        header.extend(env.tasks.iter().map(|t| md(t)));
        header.push("average".to_string());
        let mut table = Table::new(header);
        for row in &env.rows {
            let (a, b) = row.iterations;
            let iters = if a == b { a.to_string() } else { format!("{a}–{b}") };
            let mut cells = vec![md(&row.method), row.n_seeds.to_string(), iters];
            for s in row.tasks.iter().chain([&row.average]) {
                cells.push(match s {
                    Some(s) if s.n != row.n_seeds => {
                        format!("{:.4} ± {:.4} (n={})", s.mean, s.std, s.n)
                    }
                    Some(s) => format!("{:.4} ± {:.4}", s.mean, s.std),
                    None => "—".to_string(),
                });
            }
            table.push(cells);
        }
        out.push_str(&table.markdown(Rule::Spaced));
        out.push('\n');
    }
    out
}

/// `offline.csv`: `env,method,task,metric,mean,std,n_seeds`, `metric` always `action_mse`.
pub(crate) fn csv(envs: &[OfflineEnv]) -> String {
    let mut out =
        csv_line(&["env", "method", "task", "metric", "mean", "std", "n_seeds"].map(String::from));
    for env in envs {
        for row in &env.rows {
            for (task, s) in task_cells(&env.tasks, &row.tasks, row.average) {
                out.push_str(&csv_line(&[
                    env.env.clone(),
                    row.method.clone(),
                    task.to_string(),
                    pdt_rundir::OFFLINE_METRIC.to_string(),
                    num(s.mean),
                    num(s.std),
                    s.n.to_string(),
                ]));
            }
        }
    }
    out
}
