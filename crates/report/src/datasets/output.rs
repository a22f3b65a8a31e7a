//! Rendering a family: the markdown report, the CSV table and the returns figure.

use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::Path;

use pdt_base::table::{Align, Rule, Table};

use super::bars::{percent, reference_bar};
use super::level_mode;
use super::{FamilyReport, ReturnStat, TaskMean};
use crate::error::ReportError;
use crate::plot::{self, Curve, Labels, XAxis, PALETTE};
use crate::render::{csv_line, md, num, warnings_markdown};

fn cell(s: Option<ReturnStat>) -> String {
    match s {
        Some(ReturnStat { mean, std, success: Some(r), .. }) => {
            format!("{mean:.2} ± {std:.2} (success {:.0} %)", 100.0 * r)
        }
        Some(s) => format!("{:.2} ± {:.2}", s.mean, s.std),
        None => "—".to_string(),
    }
}

/// `dataset_returns_<env>.md`: the table, the means over tasks and the bars. Warnings are
/// appended so the numbers are never read without their caveats.
pub(super) fn family_markdown(
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
         recomputed from the data files (for Meta-World reach also the share of episodes that \
         succeeded, i.e. reached a reward of 10, the hand within 0.05 of the goal; for Dial the \
         share that reached the digit, a reward of 1). `reference`: the reference's `expert` \
         file, else its \
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
    let align = vec![Align::Right; header.len()];
    let mut table = Table::with_align(header, align);
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
        table.push(cells);
    }
    let mean_cell = |m: Option<TaskMean>| m.map_or("—".to_string(), |m| format!("{:.2}", m.mean));
    let mut cells = vec!["**mean**".to_string()];
    cells.extend(f.mode_means.iter().map(|m| mean_cell(*m)));
    cells.push(mean_cell(f.reference_mean));
    cells.extend(["", ""].map(String::from));
    if has_bar {
        cells.push(String::new());
    }
    table.push(cells);
    out.push_str(&table.markdown(Rule::Spaced));
    out.push('\n');

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
pub(super) fn family_csv(f: &FamilyReport) -> String {
    let mut header = vec!["task".to_string()];
    // Families whose success shows in the rewards (Meta-World reach) get a success column per mode.
    let success = pdt_envs::success_reward(&f.env).is_some();
    for m in &f.modes {
        header.extend([format!("{m}_mean"), format!("{m}_std"), format!("{m}_episodes")]);
        if success {
            header.push(format!("{m}_success_rate"));
        }
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
            if success {
                row.push(opt(s.and_then(|s| s.success)));
            }
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
pub(super) fn family_figure(f: &FamilyReport, png_name: &str) -> Result<plot::Figure, ReportError> {
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
