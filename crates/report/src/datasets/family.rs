//! Building a [`FamilyReport`]: per-task returns of our modes and the reference, and the bars.

use std::collections::{BTreeMap, BTreeSet};

use super::bars::{
    evaluate_mean_bar, evaluate_medium_bar, evaluate_reference_bar, evaluate_success_bar, mean_bar,
    reference_bar,
};
use super::{level_mode, FamilyReport, RefData, ReturnStat, TaskMean, TaskRow};

/// The standard modes in display order; D_i before P_i, best data first.
const MODE_ORDER: [&str; 6] =
    ["expert", "medium", "random", "prompt-expert", "prompt-medium", "prompt-random"];

fn mode_rank(mode: &str) -> (usize, String) {
    let rank = MODE_ORDER.iter().position(|m| *m == mode).unwrap_or(MODE_ORDER.len());
    (rank, mode.to_string())
}

pub(super) fn build_family(
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
    if pdt_envs::success_reward(env).is_some() {
        bars.push(evaluate_success_bar(&modes, &tasks, expert_mode.as_deref()));
    }

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
