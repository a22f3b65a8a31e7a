//! The report's files: `REPORT.md` (the cells next to the paper, the claims, the layout tables),
//! `cells.csv` and `curves.csv`.

use super::*;
use pdt_base::device::Matmul;

fn opt(v: Option<f64>, d: usize) -> String {
    v.map_or("-".into(), |v| format!("{v:.d$}"))
}

fn stat(s: Option<Stat>, d: usize) -> String {
    s.map_or("-".into(), |s| {
        if s.n > 1 {
            format!("{:.d$} ± {:.d$}", s.mean, s.std)
        } else {
            format!("{:.d$}", s.mean)
        }
    })
}

/// Whether any cell of `r` has the paper's value: else its tables show no paper columns and its
/// claims are not called the paper's (a user's experiment, or one of ours the paper has no number for).
pub(crate) fn has_paper(r: &Report) -> bool {
    r.cells.iter().any(|c| c.paper.is_some())
}

/// ` (bf16)` for a report of bf16 runs, after its title and each cell; nothing for fp32 (whose
/// reports read as before) or tf32.
fn precision_tag(r: &Report) -> &'static str {
    if r.matmul == Matmul::Bf16 {
        " (bf16)"
    } else {
        ""
    }
}

pub(super) fn markdown(m: &Manifest, r: &Report) -> String {
    let mut s = String::new();
    // The paper's columns only where a cell has a paper value (a user's experiment has none).
    let paper = has_paper(r);
    let _ = writeln!(s, "# {} — `{}` budget{}\n", r.title, r.budget, precision_tag(r));
    if r.matmul == Matmul::Bf16 {
        let _ = writeln!(
            s,
            "Trained in bf16 mixed precision (`run.matmul = \"bf16\"`, experimental: its fidelity \
             against fp32 is not yet measured): every cell below is a bf16 result.\n"
        );
    }
    let _ = writeln!(s, "{}\n", m.description.trim());
    let _ = writeln!(s, "Budget: {}\n", r.budget_note.trim());
    let _ = writeln!(
        s,
        "Ours: mean ± std over seeds of the average return on the test tasks at the last evaluation; \
         normalised = 100 (R - R_random) / (R_expert - R_random) per test task with our datasets' \
         returns, averaged (the per-task mean of ratios: the claims judge it, docs/reproduce.md#claims). \
         Ratio of means: the mean return over the test tasks normalised by the mean expert and mean \
         random returns over them, the paper's way{}",
        match paper {
            true => " and the one compared with the paper's value. Paper normalised: the paper's \
                     value with the reference release's expert returns (its prompt files) and our \
                     random returns; `-` where the reference's experts are unknown. Within: |ours \
                     (ratio of means) - paper| <= the paper's std, normalised (only where the paper \
                     gives a std).\n",
            false => ".\n",
        }
    );
    let (text, num) = (Align::Left, Align::Right);
    let mut header = "cell|seeds|iteration|ours|ours normalised|evaluation noise|ratio of means"
        .split('|')
        .map(String::from)
        .collect::<Vec<_>>();
    let mut align = vec![text, num, num, num, num, num, num];
    if paper {
        header.extend(["paper", "paper normalised", "within paper std"].map(String::from));
        align.extend([num, num, text]);
    }
    header.push("status".into());
    align.push(text);
    let mut table = Table::with_align(header, align);
    for c in &r.cells {
        let PaperText { raw: paper_raw, normalised: pn } = PaperText::of(c);
        let it = match (c.iteration, c.iterations_planned) {
            (Some(i), Some(n)) => format!("{i} / {n}"),
            (None, Some(n)) => format!("- / {n}"),
            _ => "-".into(),
        };
        let mut row = vec![
            format!("`{}`{}", c.id, precision_tag(r)),
            c.seeds.to_string(),
            it,
            match c.success {
                Some(sr) => format!("{} (success {:.0} %)", stat(c.ours, 2), 100.0 * sr.mean),
                None => stat(c.ours, 2),
            },
            stat(c.ours_normalised, 1),
            eval_noise_text(c),
            stat(c.ours_normalised_rom, 1),
        ];
        if paper {
            let within = c.within_paper_std.map_or("-", |w| if w { "yes" } else { "no" });
            row.extend([paper_raw, pn, within.to_string()]);
        }
        row.push(c.status.to_string());
        table.push(row);
    }
    s.push_str(&table.markdown(Rule::Tight));
    if m.layout == Layout::Table {
        let mut rows: Vec<String> = Vec::new();
        let mut cols: Vec<String> = Vec::new();
        for c in &r.cells {
            if let (Some(row), Some(col)) = (&c.row, &c.column) {
                if !rows.contains(row) {
                    rows.push(row.clone());
                }
                if !cols.contains(col) {
                    cols.push(col.clone());
                }
            }
        }
        let _ = match paper {
            true => writeln!(s, "\n## As the paper lays it out (ours normalised as a ratio of means / paper normalised; raw in the table above)\n"),
            false => writeln!(s, "\n## As a table (ours normalised as a ratio of means; raw in the table above)\n"),
        };
        // The corner cell is empty: the rows are labelled, the columns are.
        let mut header = vec![String::new()];
        header.extend(cols.iter().cloned());
        let mut layout = Table::new(header);
        for row in &rows {
            let line: Vec<String> = cols
                .iter()
                .map(|col| {
                    r.cells
                        .iter()
                        .find(|c| c.row.as_ref() == Some(row) && c.column.as_ref() == Some(col))
                        .map_or("".into(), |c| match paper {
                            true => format!(
                                "{} / {}",
                                stat(c.ours_normalised_rom, 1),
                                opt(c.paper_normalised, 1)
                            ),
                            false => stat(c.ours_normalised_rom, 1),
                        })
                })
                .collect();
            let mut cells = vec![row.clone()];
            cells.extend(line);
            layout.push(cells);
        }
        s.push_str(&layout.markdown(Rule::Tight));
    }
    if r.cells.iter().any(|c| !c.problems.is_empty()) {
        let _ = writeln!(s, "\n## What could not be read\n");
        for c in &r.cells {
            for p in &c.problems {
                let _ = writeln!(s, "- `{}`: {p}", c.id);
            }
        }
    }
    if !r.claims.is_empty() {
        let whose = if paper { "The paper's claims" } else { "The claims" };
        let _ = writeln!(s, "\n## {whose}, on these numbers\n");
        for c in &r.claims {
            let _ = writeln!(s, "- **{}**: {} ({})", c.text, c.verdict, c.detail);
        }
    }
    let _ =
        writeln!(s, "\nFiles: `cells.csv`, `curves.csv`, `report.json`, `curves_<env>.png/.svg`.");
    s
}

/// A cell's evaluation noise as the tables print it: the SD over repeats of the normalised score
/// and how many repeats (`-`: not measured, the runs were evaluated once).
pub(crate) fn eval_noise_text(c: &CellResult) -> String {
    c.eval_noise.map_or("-".into(), |n| format!("{:.1} ({} repeats)", n.sd, n.repeats))
}

pub(super) fn cells_csv(r: &Report) -> String {
    let mut s = String::from(
        "cell,env,label,row,column,status,seeds,iteration,iterations_planned,ours_mean,ours_std,\
         ours_normalised_mean,ours_normalised_std,paper,paper_std,paper_normalised,paper_normalised_std,within_paper_std,paper_source,success_mean,success_std,\
         ours_normalised_sample_sd,ours_normalised_ci_lo,ours_normalised_ci_hi,ours_normalised_iqm,\
         ours_normalised_ratio_of_means_mean,ours_normalised_ratio_of_means_std,\
         eval_noise_sd,eval_noise_repeats\n",
    );
    let f = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v}"));
    let q = |v: &str| format!("\"{}\"", v.replace('"', "\"\""));
    for c in &r.cells {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            q(&c.id),
            c.env,
            q(&c.label),
            q(c.row.as_deref().unwrap_or("")),
            q(c.column.as_deref().unwrap_or("")),
            q(&c.status),
            c.seeds,
            c.iteration.map_or(String::new(), |i| i.to_string()),
            c.iterations_planned.map_or(String::new(), |i| i.to_string()),
            f(c.ours.map(|s| s.mean)),
            f(c.ours.map(|s| s.std)),
            f(c.ours_normalised.map(|s| s.mean)),
            f(c.ours_normalised.map(|s| s.std)),
            f(c.paper),
            f(c.paper_std),
            f(c.paper_normalised),
            f(c.paper_normalised_std),
            c.within_paper_std.map_or(String::new(), |w| w.to_string()),
            q(c.paper_source.as_deref().unwrap_or("")),
            f(c.success.map(|s| s.mean)),
            f(c.success.map(|s| s.std)),
            f(c.normalised_stats.as_ref().and_then(|s| s.sd)),
            f(c.normalised_stats.as_ref().map(|s| s.ci.lo)),
            f(c.normalised_stats.as_ref().map(|s| s.ci.hi)),
            f(c.normalised_stats.as_ref().and_then(|s| s.iqm)),
            f(c.ours_normalised_rom.map(|s| s.mean)),
            f(c.ours_normalised_rom.map(|s| s.std)),
            f(c.eval_noise.map(|n| n.sd)),
            c.eval_noise.map_or(String::new(), |n| n.repeats.to_string()),
        );
    }
    s
}

/// One row per cell and evaluated iteration: the average test return and, where the cell's runs
/// logged it at that iteration, their training loss (`loss_metric` names its column).
pub(super) fn curves_csv(r: &Report) -> String {
    let mut s =
        String::from("cell,iteration,return_mean,return_std,loss_metric,loss_mean,loss_std\n");
    for c in &r.cells {
        for (i, m, sd) in &c.curve {
            let loss = c.loss_curve.iter().find(|(it, _, _)| it == i);
            let (metric, lm, ls) = match (loss, &c.loss_metric) {
                (Some((_, lm, ls)), Some(metric)) => {
                    (metric.as_str(), lm.to_string(), ls.to_string())
                }
                _ => ("", String::new(), String::new()),
            };
            let _ = writeln!(s, "\"{}\",{i},{m},{sd},{metric},{lm},{ls}", c.id);
        }
    }
    s
}

/// A cell's paper value as the report's tables print it: raw (`927.20 ± 18.02`, or `≈ 930.0` read
/// off a figure) and normalised; `-` where the paper gives none.
pub(crate) struct PaperText {
    pub raw: String,
    pub normalised: String,
}

impl PaperText {
    pub(crate) fn of(c: &CellResult) -> Self {
        let raw = match (c.paper, c.paper_std) {
            (Some(p), Some(sd)) => format!("{p:.2} ± {sd:.2}"),
            (Some(p), None) => format!("≈ {p:.1}"),
            _ => "-".into(),
        };
        let normalised = match (c.paper_normalised, c.paper_normalised_std) {
            (Some(p), Some(sd)) => format!("{p:.1} ± {sd:.1}"),
            (Some(p), None) => format!("≈ {p:.1}"),
            _ => "-".into(),
        };
        PaperText { raw, normalised }
    }
}
