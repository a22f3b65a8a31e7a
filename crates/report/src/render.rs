//! Text outputs: the Markdown table a researcher reads and the CSV files a script reads.

use std::fmt::Write as _;

use pdt_base::table::{Rule, Table};

use crate::aggregate::{Aggregated, Stat};

/// Formats a float for CSV: shortest round-trip form, so no precision is lost.
pub(crate) fn num(v: f64) -> String {
    format!("{v}")
}

fn opt_num(v: Option<f64>) -> String {
    v.map(num).unwrap_or_default()
}

fn opt_int(v: Option<u64>) -> String {
    v.map(|x| x.to_string()).unwrap_or_default()
}

/// Quotes a CSV field when it needs it (RFC 4180).
fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) || s.starts_with(' ') || s.ends_with(' ') {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

pub(crate) fn csv_line(fields: &[String]) -> String {
    let mut line = fields.iter().map(|f| csv_field(f)).collect::<Vec<_>>().join(",");
    line.push('\n');
    line
}

/// A row's cells for a CSV: each task with a value (`tasks` and `stats` aligned), then the row's
/// `average` as a task of that name.
pub(crate) fn task_cells<'a>(
    tasks: &'a [String],
    stats: &'a [Option<Stat>],
    average: Option<Stat>,
) -> impl Iterator<Item = (&'a str, Stat)> + 'a {
    tasks
        .iter()
        .zip(stats)
        .filter_map(|(t, s)| s.map(|s| (t.as_str(), s)))
        .chain(average.map(|s| ("average", s)))
}

/// `table.csv`: one row per (env, method, task), plus an `average` task per (env, method).
pub(crate) fn table_csv(agg: &Aggregated) -> String {
    let mut out = csv_line(&["env", "method", "task", "mean", "std", "n_seeds"].map(String::from));
    for env in &agg.envs {
        for row in &env.rows {
            for (task, s) in task_cells(&env.tasks, &row.tasks, row.average) {
                out.push_str(&csv_line(&[
                    env.env.clone(),
                    row.method.clone(),
                    task.to_string(),
                    num(s.mean),
                    num(s.std),
                    s.n.to_string(),
                ]));
            }
        }
    }
    out
}

/// `curves.csv`: the plotted numbers.
pub(crate) fn curves_csv(agg: &Aggregated) -> String {
    let mut out =
        csv_line(&["env", "method", "iteration", "mean", "std", "n_seeds"].map(String::from));
    for env in &agg.envs {
        for c in &env.curves {
            for p in &c.points {
                out.push_str(&csv_line(&[
                    env.env.clone(),
                    c.method.clone(),
                    p.iteration.to_string(),
                    num(p.stat.mean),
                    num(p.stat.std),
                    p.stat.n.to_string(),
                ]));
            }
        }
    }
    out
}

/// `runs.csv`: one row per run found, including the ones left out, so that a reader can see
/// exactly which runs each mean is made of.
pub(crate) fn runs_csv(agg: &Aggregated) -> String {
    let mut out = csv_line(
        &[
            "run_dir",
            "name",
            "env",
            "split",
            "method",
            "seed",
            "used",
            "final_source",
            "final_iteration",
            "final_average_return",
            "n_test_tasks",
            "n_curve_points",
            "last_train_iteration",
            "loss_metric",
            "last_loss",
            "elapsed_s",
        ]
        .map(String::from),
    );
    for r in &agg.runs {
        out.push_str(&csv_line(&[
            r.dir.display().to_string(),
            r.name.clone(),
            r.env.clone(),
            r.split.clone(),
            r.method.clone(),
            opt_int(r.seed),
            r.final_source.is_some().to_string(),
            r.final_source.unwrap_or_default().to_string(),
            opt_int(r.final_iteration),
            opt_num(r.final_average),
            r.n_test_tasks.to_string(),
            r.n_curve_points.to_string(),
            opt_int(r.last_train_iteration),
            r.loss_metric.clone(),
            opt_num(r.last_loss),
            opt_num(r.elapsed_s),
        ]));
    }
    out
}

/// Escapes text for a Markdown table cell.
pub(crate) fn md(s: &str) -> String {
    s.replace('|', "\\|")
}

/// "mean ± std" with two decimals, like the paper's tables; "(n=k)" flags a cell that fewer
/// seeds than the method's total contribute to.
fn cell(s: &Stat, n_seeds: usize, bold: bool) -> String {
    let mut text = format!("{:.2} ± {:.2}", s.mean, s.std);
    if bold {
        text = format!("**{text}**");
    }
    if s.n != n_seeds {
        let _ = write!(text, " (n={})", s.n);
    }
    text
}

/// Index of the method with the highest finite mean in a column, if more than one method
/// competes (bolding a lone method would say nothing).
fn best(stats: &[Option<Stat>]) -> Option<usize> {
    if stats.iter().filter(|s| s.is_some()).count() < 2 {
        return None;
    }
    stats
        .iter()
        .enumerate()
        .filter_map(|(i, s)| s.filter(|s| s.mean.is_finite()).map(|s| (i, s.mean)))
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// `table.md`: one table per environment; rows are methods, columns the test tasks and their
/// average. Warnings are appended so that the table is never read without its caveats.
/// `offline` is the action-error section (`crate::offline::markdown`), after the returns' tables
/// and before the warnings.
pub(crate) fn table_markdown(
    agg: &Aggregated,
    title: Option<&str>,
    warnings: &[String],
    offline: &str,
) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "# {}\n", md(title.unwrap_or("Prompt-DT results")));
    if !agg.envs.is_empty() {
        returns_intro(&mut out, agg);
    }
    for env in &agg.envs {
        env_table(&mut out, env);
    }
    out.push_str(offline);
    warnings_markdown(&mut out, warnings);
    out
}

/// What the returns' tables show, and how many runs they use.
fn returns_intro(out: &mut String, agg: &Aggregated) {
    let _ = writeln!(
        out,
        "Return on held-out test tasks at the end of training, mean ± std over seeds \
         (population std). A seed's value is from `eval_final.json` if present, else its last \
         complete test evaluation in `eval.jsonl`; `average` is each seed's mean over its test \
         tasks, then mean ± std over seeds. Best mean per column in bold; (n=k): only k seeds \
         contribute (task not evaluated, or a non-finite return).\n"
    );
    let skipped = match agg.runs_skipped {
        0 => String::new(),
        n => format!(", {n} left out (see warnings)"),
    };
    // Runs without an environment have action errors, not returns: shown in their own section.
    let offline = match agg.offline_only {
        0 => String::new(),
        n => format!(", {n} evaluated offline only (the action-error section below)"),
    };
    let _ = writeln!(out, "{} run(s) used{skipped}{offline}.\n", agg.runs_used);
}

/// One environment's table of returns.
fn env_table(out: &mut String, env: &crate::aggregate::EnvReport) {
    let _ = writeln!(out, "## {}\n", md(&env.env));
    let mut header = vec!["method".to_string(), "seeds".to_string(), "iteration".to_string()];
    header.extend(env.tasks.iter().map(|t| md(t)));
    header.push("average".to_string());
    // The method column left-aligned, the numbers right-aligned.
    let mut table = Table::new(header);

    let best_task: Vec<Option<usize>> = (0..env.tasks.len())
        .map(|j| best(&env.rows.iter().map(|r| r.tasks[j]).collect::<Vec<_>>()))
        .collect();
    let best_avg = best(&env.rows.iter().map(|r| r.average).collect::<Vec<_>>());
    for (i, row) in env.rows.iter().enumerate() {
        let iters = match row.iterations {
            Some((a, b)) if a == b => a.to_string(),
            Some((a, b)) => format!("{a}–{b}"),
            None => "—".to_string(),
        };
        let mut cells = vec![md(&row.method), row.n_seeds.to_string(), iters];
        for (j, s) in row.tasks.iter().enumerate() {
            cells.push(match s {
                Some(s) => cell(s, row.n_seeds, best_task[j] == Some(i)),
                None => "—".to_string(),
            });
        }
        cells.push(match &row.average {
            Some(s) => cell(s, row.n_seeds, best_avg == Some(i)),
            None => "—".to_string(),
        });
        table.push(cells);
    }
    out.push_str(&table.markdown(Rule::Spaced));
    out.push('\n');
}

/// A `## Warnings` section listing `warnings` (nothing when there are none).
pub(crate) fn warnings_markdown(out: &mut String, warnings: &[String]) {
    if warnings.is_empty() {
        return;
    }
    let _ = writeln!(out, "## Warnings\n");
    for w in warnings {
        // Indented continuation keeps multi-line warnings inside their list item.
        let _ = writeln!(out, "- {}", md(w).replace('\n', "\n  "));
    }
    out.push('\n');
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_quoting() {
        assert_eq!(csv_field("plain"), "plain");
        assert_eq!(csv_field("a,b"), "\"a,b\"");
        assert_eq!(csv_field("say \"hi\""), "\"say \"\"hi\"\"\"");
    }

    #[test]
    fn best_needs_two_competitors() {
        let a = Stat { mean: 1.0, std: 0.0, n: 1 };
        let b = Stat { mean: 2.0, ..a };
        assert_eq!(best(&[Some(a), None]), None);
        assert_eq!(best(&[Some(a), Some(b)]), Some(1));
    }
}
