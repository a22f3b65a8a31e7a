//! `reproduce EXP --budget B --status`: where each run of a plan stands (finished, archived,
//! stopped part-way, not started), without running or writing anything. A long sweep on a small
//! machine is stopped and resumed many times; this is what tells its owner what is left, and the
//! command that goes on is the same `reproduce` without `--status`.

use crate::plan::{self, Plan, RunState};
use crate::registry::PROVENANCE_JSON;
use pdt_base::table::{Align, Table};
use pdt_rundir::{MetricsLine, RunDir};
use std::io::BufRead;
use std::path::Path;

/// One run of a plan and where it stands.
#[derive(Debug, Clone, PartialEq)]
pub struct RunStatus {
    /// `<cell id>/<budget>/seed<N>`.
    pub key: String,
    pub progress: Progress,
    /// The results registry holds this run (`results/<key>/`).
    pub archived: bool,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Progress {
    /// Its run directory reached the budget's last iteration.
    Finished,
    /// Stopped part-way: `reproduce` resumes it from `resume_from`; `logged` is the last
    /// iteration in its `metrics.jsonl` (training after the resume point is done again).
    Partial { resume_from: u64, logged: Option<u64>, of: u64 },
    /// No run directory with a resume point: `reproduce` starts it (or an archived run whose
    /// directory is elsewhere: `archived` says so).
    NotStarted,
    /// Its directory cannot be resumed as it is (another configuration, a lost commit record).
    Problem(String),
}

/// Where each of `plan`'s runs stands; `registry` is the results registry (`results/`).
pub fn runs(plan: &Plan, registry: &Path) -> Vec<RunStatus> {
    plan.runs
        .iter()
        .map(|r| {
            let archived = registry.join(&r.key).join(PROVENANCE_JSON).is_file();
            let progress = match plan::state(r) {
                Ok(RunState::Finished) => Progress::Finished,
                Ok(RunState::New) => Progress::NotStarted,
                Ok(RunState::Partial { iteration }) => Progress::Partial {
                    resume_from: iteration,
                    logged: last_logged(&RunDir::at(&r.dir).metrics_path()),
                    of: r.config.train.iterations,
                },
                Err(e) => Progress::Problem(e.to_string()),
            };
            RunStatus { key: r.key.clone(), progress, archived }
        })
        .collect()
}

/// The iteration of the last complete line of a `metrics.jsonl` (a line being written is skipped).
fn last_logged(path: &Path) -> Option<u64> {
    let (file, _) = pdt_base::fs::open_regular(path).ok()?; // a FIFO is skipped, not blocked on
    std::io::BufReader::new(file)
        .lines()
        .map_while(Result::ok)
        .filter_map(|l| serde_json::from_str::<MetricsLine>(&l).ok())
        .map(|m| m.iteration)
        .last()
}

/// The counts a status table ends with.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Tally {
    pub runs: usize,
    /// Finished here, or archived (a fresh clone's registry).
    pub done: usize,
    pub archived: usize,
    pub partial: usize,
    pub not_started: usize,
    pub problems: usize,
}

impl Tally {
    pub fn of(runs: &[RunStatus]) -> Self {
        let mut t = Tally { runs: runs.len(), ..Default::default() };
        for r in runs {
            t.archived += usize::from(r.archived);
            match &r.progress {
                Progress::Finished => t.done += 1,
                Progress::NotStarted | Progress::Partial { .. } if r.archived => t.done += 1,
                Progress::Partial { .. } => t.partial += 1,
                Progress::NotStarted => t.not_started += 1,
                Progress::Problem(_) => t.problems += 1,
            }
        }
        t
    }

    /// Whether a run is left to do (part-way, not started, or one that cannot be resumed).
    pub fn unfinished(&self) -> bool {
        self.partial + self.not_started + self.problems > 0
    }

    /// `--status`'s closing line: how many runs of `plan` stand where, with the registry read.
    pub fn summary(&self, plan: &Plan, registry: &Path) -> String {
        let problems = match self.problems {
            0 => String::new(),
            n => format!(", {n} cannot be resumed as they are"),
        };
        format!(
            "{} runs of {} at the {} budget: {} done ({} archived in {}), {} part-way, {} not \
             started{problems}",
            self.runs,
            plan.experiment,
            plan.budget,
            self.done,
            self.archived,
            registry.display(),
            self.partial,
            self.not_started,
        )
    }
}

/// A run's state as the status table prints it.
pub fn describe(r: &RunStatus) -> String {
    let what = match &r.progress {
        Progress::Finished => "finished".to_string(),
        Progress::Partial { resume_from, logged, of } => match logged {
            Some(l) if l > resume_from => {
                format!("at iteration {l} of {of} (resumes from {resume_from})")
            }
            _ => format!("at iteration {resume_from} of {of}"),
        },
        Progress::NotStarted if r.archived => "archived (no run directory here)".to_string(),
        Progress::NotStarted => "not started".to_string(),
        Progress::Problem(why) => format!("cannot resume: {why}"),
    };
    match (&r.progress, r.archived) {
        (Progress::Finished, true) => format!("{what}, archived"),
        (Progress::Partial { .. }, true) => format!("{what}; an archived copy is in the registry"),
        _ => what,
    }
}

/// The status table, as aligned text: a row per run.
pub fn table(runs: &[RunStatus]) -> String {
    let mut t =
        Table::with_align(vec!["run".into(), "state".into()], vec![Align::Left, Align::Left]);
    for r in runs {
        t.push(vec![r.key.clone(), describe(r)]);
    }
    t.aligned_text()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn st(progress: Progress, archived: bool) -> RunStatus {
        RunStatus { key: "k".into(), progress, archived }
    }

    #[test]
    fn tally_counts_an_archived_run_as_done_wherever_its_directory_is() {
        let p = |r, l| Progress::Partial { resume_from: r, logged: l, of: 500 };
        let runs = [
            st(Progress::Finished, true),
            st(Progress::Finished, false),
            st(Progress::NotStarted, true),
            st(Progress::NotStarted, false),
            st(p(350, Some(361)), false),
            st(Progress::Problem("x".into()), false),
        ];
        let t = Tally::of(&runs);
        let want = Tally { runs: 6, done: 3, archived: 2, partial: 1, not_started: 1, problems: 1 };
        assert_eq!(t, want);
        assert_eq!(describe(&runs[4]), "at iteration 361 of 500 (resumes from 350)");
        assert_eq!(describe(&st(p(350, Some(350)), false)), "at iteration 350 of 500");
        assert_eq!(describe(&runs[0]), "finished, archived");
        assert_eq!(describe(&runs[2]), "archived (no run directory here)");
    }
}
