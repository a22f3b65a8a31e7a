//! The paper's claims judged on the cells' per-task normalised scores by the rule of
//! [`crate::stats`] (docs/reproduce.md#claims): a bootstrap interval of the difference read against
//! the claim's margin, provisional below three seeds a side.

use super::CellResult;
use crate::manifest::{Claim, ClaimKind};
use crate::stats::{self, Call, Judgement};

/// A checked claim.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ClaimResult {
    pub text: String,
    /// `holds`, `fails`, `undecided`, `provisional (n vs m seeds)` (fewer than
    /// [`stats::MIN_SEEDS`] seeds in a cell: the detail says what the interval says), or
    /// `not measured`.
    pub verdict: String,
    pub detail: String,
}

/// The margin of a `better` claim without `min_margin`, and of an `insensitive` one without
/// `max_spread`: normalised points.
pub const DEFAULT_MARGIN: f64 = 10.0;

pub(super) fn check_claim(c: &Claim, cells: &[CellResult]) -> ClaimResult {
    let cell = |id: &str| cells.iter().find(|x| x.id == id);
    // Only cells with a finished seed count: a claim checked on a model still at iteration 1
    // would read "fails" for no reason.
    let scores = |id: &str| {
        cell(id)
            .filter(|x| x.seeds_finished > 0 && !x.seed_task_scores.is_empty())
            .map(|x| x.seed_task_scores.as_slice())
    };
    let fmt = |id: &str| {
        let Some(x) = cell(id) else { return format!("{id}: -") };
        let value = x.ours_normalised.map_or("-".into(), |s| format!("{:.1}", s.mean));
        match x.iteration.filter(|_| x.seeds_finished == 0) {
            Some(it) => format!("{id}: {value} so far (running, iteration {it})"),
            None => format!("{id}: {value}"),
        }
    };
    let ids: Vec<&str> = match c.kind {
        ClaimKind::Better => vec![c.a.as_deref().unwrap_or(""), c.b.as_deref().unwrap_or("")],
        ClaimKind::Insensitive | ClaimKind::Ordered => c.cells.iter().map(String::as_str).collect(),
    };
    let Some(data) = ids.iter().map(|id| scores(id).map(|s| (*id, s))).collect::<Option<Vec<_>>>()
    else {
        let detail = ids.iter().map(|id| fmt(id)).collect::<Vec<_>>().join(" vs ");
        return not_measured(c, detail);
    };
    let judged = match c.kind {
        ClaimKind::Better => {
            stats::judge_better(data[0], data[1], c.min_margin.unwrap_or(DEFAULT_MARGIN))
        }
        ClaimKind::Insensitive => {
            stats::judge_similar(&data, c.max_spread.unwrap_or(DEFAULT_MARGIN))
        }
        ClaimKind::Ordered => ordered(&data),
    };
    match judged {
        Some(j) => ClaimResult {
            text: c.text.clone(),
            verdict: j.verdict,
            detail: format!("normalised, per-task mean of ratios: {}", j.detail),
        },
        None => not_measured(c, ids.iter().map(|id| fmt(id)).collect::<Vec<_>>().join(" vs ")),
    }
}

/// "The cells score in the order listed": each consecutive pair a `better` claim with margin 0;
/// holds when every pair holds, fails when one fails.
fn ordered(data: &[(&str, &stats::Scores)]) -> Option<Judgement> {
    let pairs: Vec<Judgement> =
        data.windows(2).map(|w| stats::judge_better(w[0], w[1], 0.0)).collect::<Option<_>>()?;
    let call = if pairs.iter().all(|j| j.call == Call::Holds) {
        Call::Holds
    } else if pairs.iter().any(|j| j.call == Call::Fails) {
        Call::Fails
    } else {
        Call::Undecided
    };
    let provisional = pairs.iter().find(|j| j.verdict.starts_with("provisional"));
    Some(Judgement {
        verdict: match provisional {
            Some(_) => {
                let seeds: Vec<String> = data.iter().map(|(_, s)| s.len().to_string()).collect();
                format!("provisional ({} seeds)", seeds.join(" vs "))
            }
            None => call.word().into(),
        },
        detail: pairs.iter().map(|j| j.detail.as_str()).collect::<Vec<_>>().join("; "),
        call,
    })
}

fn not_measured(c: &Claim, detail: String) -> ClaimResult {
    ClaimResult { text: c.text.clone(), verdict: "not measured".into(), detail }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pdt_report::Stat;

    fn cell(id: &str, scores: Vec<Vec<f64>>) -> CellResult {
        let means: Vec<f64> =
            scores.iter().map(|t| t.iter().sum::<f64>() / t.len() as f64).collect();
        CellResult {
            id: id.into(),
            env: "ant_dir".into(),
            label: id.into(),
            row: None,
            column: None,
            status: "ran".into(),
            seeds: scores.len(),
            seeds_finished: scores.len(),
            iteration: Some(500),
            iterations_planned: Some(500),
            ours: None,
            ours_normalised: Stat::of(&means),
            ours_normalised_rom: None,
            normalised_stats: stats::cell_stats(&scores),
            seed_task_scores: scores,
            success: None,
            eval_noise: None,
            paper: None,
            paper_std: None,
            paper_source: None,
            paper_normalised: None,
            paper_normalised_std: None,
            within_paper_std: None,
            curve: vec![],
            loss_metric: None,
            loss_curve: vec![],
            problems: vec![],
        }
    }

    fn claim(kind: ClaimKind, margin: Option<f64>) -> Claim {
        Claim {
            text: "a vs b".into(),
            kind,
            a: Some("a".into()),
            b: Some("b".into()),
            cells: vec!["a".into(), "b".into()],
            max_spread: margin,
            min_margin: margin,
        }
    }

    #[test]
    fn a_manifest_claim_is_judged_by_the_bootstrap_rule() {
        let (a, b) = stats::example_scores();
        let cells = [cell("a", a.clone()), cell("b", b.clone())];
        let r = check_claim(&claim(ClaimKind::Better, None), &cells);
        assert_eq!(r.verdict, "holds", "{}", r.detail);
        assert!(r.detail.contains("3 seeds") && r.detail.contains("95 % interval"), "{}", r.detail);
        // One seed a side: never holds, however far apart.
        let one = [cell("a", vec![vec![95.0, 90.0]]), cell("b", vec![vec![5.0, 0.0]])];
        let r = check_claim(&claim(ClaimKind::Better, None), &one);
        assert_eq!(r.verdict, "provisional (1 vs 1 seeds)", "{}", r.detail);
        let r = check_claim(&claim(ClaimKind::Insensitive, Some(10.0)), &cells);
        assert_eq!(r.verdict, "fails", "{}", r.detail);
        let r = check_claim(&claim(ClaimKind::Ordered, None), &cells);
        assert_eq!(r.verdict, "holds", "{}", r.detail);
        // A cell with no finished seed is not measured, whatever the scores.
        let mut running = cell("a", a);
        running.seeds_finished = 0;
        let r = check_claim(&claim(ClaimKind::Better, None), &[running, cell("b", b)]);
        assert_eq!(r.verdict, "not measured");
    }
}
