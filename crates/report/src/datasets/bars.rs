//! The quality bars: which apply to a family, and how each is evaluated.

use std::fmt::Write as _;

use pdt_envs::DatasetBar;

use super::{level_mode, BarStatus, QualityBar, RefData, TaskMean, TaskRow};

/// A per-task bar against the reference: ours expert ≥ ref − tolerance·|ref| on every one of the
/// family's tasks (= ≥ (1 − tolerance) × ref for a positive reference). Better than the
/// reference is always fine.
pub(super) struct ReferenceBar {
    pub(super) tolerance: f64,
    tasks: usize,
    name: &'static str,
}

/// A bar on the mean expert return over the family's tasks.
pub(super) struct MeanBar {
    min: f64,
    tasks: usize,
    name: &'static str,
}

/// The family's per-task bar against the reference, if it has one
/// ([`pdt_envs::EnvFamily::dataset_bar`]); over all of the family's tasks.
pub(super) fn reference_bar(env: &str) -> Option<ReferenceBar> {
    let family = pdt_envs::family(env).ok()?;
    match family.dataset_bar()? {
        DatasetBar::Reference { tolerance, name } => {
            Some(ReferenceBar { tolerance, tasks: family.num_tasks(), name })
        }
        DatasetBar::Mean { .. } => None,
    }
}

/// The family's bar on the mean expert return, if it has one; over all of the family's tasks.
pub(super) fn mean_bar(env: &str) -> Option<MeanBar> {
    let family = pdt_envs::family(env).ok()?;
    match family.dataset_bar()? {
        DatasetBar::Mean { min, name } => Some(MeanBar { min, tasks: family.num_tasks(), name }),
        DatasetBar::Reference { .. } => None,
    }
}

pub(super) fn evaluate_reference_bar(
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

pub(super) fn evaluate_mean_bar(
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
pub(super) fn evaluate_medium_bar(modes: &[String], tasks: &[TaskRow]) -> QualityBar {
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

pub(super) fn join_indices(v: &[usize]) -> String {
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

pub(super) fn percent(x: f64) -> String {
    format!("{:+.1} %", 100.0 * x)
}

/// Families with a success criterion (Meta-World reach): the expert data succeed in every episode
/// of every task (the scripted expert's promise, spec: Meta-World requires >= 98 % at this noise).
pub(super) fn evaluate_success_bar(
    modes: &[String],
    tasks: &[TaskRow],
    expert_mode: Option<&str>,
) -> QualityBar {
    let name = "expert succeeds in every episode of every task".to_string();
    let Some(j) = expert_mode.and_then(|e| modes.iter().position(|m| m == e)) else {
        return QualityBar {
            name,
            status: BarStatus::NotEvaluated,
            detail: "no expert data".into(),
        };
    };
    let rates: Vec<(usize, f64)> =
        tasks.iter().filter_map(|t| Some((t.index, t.modes[j]?.success?))).collect();
    if rates.is_empty() {
        return QualityBar {
            name,
            status: BarStatus::NotEvaluated,
            detail: "no task has expert data".into(),
        };
    }
    let short: Vec<usize> = rates.iter().filter(|(_, r)| *r < 1.0).map(|(i, _)| *i).collect();
    let lowest = rates.iter().map(|(_, r)| *r).fold(f64::INFINITY, f64::min);
    let detail = if short.is_empty() {
        format!("100 % on all {} tasks", rates.len())
    } else {
        format!(
            "below 100 % on task{} {} (lowest {:.1} %)",
            if short.len() == 1 { "" } else { "s" },
            join_indices(&short),
            100.0 * lowest
        )
    };
    let status = if short.is_empty() { BarStatus::Met } else { BarStatus::NotMet };
    QualityBar { name, status, detail }
}
