//! The types of running a plan (`crate::exec`), apart from the running: its options, progress and
//! summary, and the flag its children get. Shared with the variants' evaluations
//! (`crate::variant`), which `crate::exec` runs.

use std::path::PathBuf;

/// How to run a plan.
#[derive(Debug, Clone)]
pub struct ExecOptions {
    /// The `promptdt` binary the children run.
    pub exe: PathBuf,
    /// Runs at once.
    pub jobs: usize,
    /// `OMP_WAIT_POLICY` given to the children (`PASSIVE`: idle OpenMP threads sleep rather than
    /// spin: a spinning thread takes a core another run needs, and runs share the cores).
    pub omp_wait_policy: Option<String>,
    /// Directory holding `pretrained/<env>/` agents (for `collect --from-pretrained`).
    pub pretrained_root: PathBuf,
    /// Runs per process: up to this many runs of one family, model shape, device and data
    /// directory train as one pack (`crate::packs`, docs/packs.md); 1: each run in its own process.
    /// A pack counts as one of `jobs`.
    pub pack: usize,
    /// The packs' engine (written into each pack's record).
    pub pack_engine: pdt_rundir::pack::Engine,
}

/// What the progress callback sees.
#[derive(Debug, Clone)]
pub struct Progress {
    pub stage: Stage,
    pub runs_total: usize,
    pub runs_finished: usize,
    /// Training iterations done and planned, over every run of the plan.
    pub iterations_done: u64,
    pub iterations_total: u64,
    /// Keys of the runs in progress.
    pub running: Vec<String>,
    /// Keys of the runs another process holds, waited for.
    pub waiting: Vec<String>,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Stage {
    Data(String),
    Training,
    Done,
}

/// What [`execute`] did.
#[derive(Debug, Clone, Default)]
pub struct ExecSummary {
    pub already_finished: usize,
    pub started: usize,
    pub resumed: usize,
    /// `(run key, message)` for every run whose process failed; the others still ran.
    pub failed: Vec<(String, String)>,
    /// Runs another process held when this one came to them, waited for.
    pub waited: Vec<String>,
    /// Of the runs waited for, those the other process finished.
    pub finished_elsewhere: usize,
    /// Temporary data directories of a killed `reproduce`, removed.
    pub removed_temps: Vec<PathBuf>,
    /// Variants' evaluations done (`crate::variant`; those done before count as finished).
    pub evaluated: usize,
}

/// The global flag that makes a `promptdt` child stop when its standard input reaches its end,
/// which happens when the parent holding the pipe's other end dies, however it dies (even
/// SIGKILL): no `collect` or `train` child outlives a killed `reproduce`. (A pipe rather than
/// `prctl(PR_SET_PDEATHSIG)`, which needs unsafe code.)
pub const DIE_WITH_PARENT: &str = "--die-with-parent";

impl Progress {
    /// The progress bar's message: which family's data are being collected, or how many runs are
    /// done, which are running and which another process holds.
    pub fn message(&self) -> String {
        if let Stage::Data(env) = &self.stage {
            return format!("collecting the {env} datasets");
        }
        let mut m = format!("runs {}/{} done", self.runs_finished, self.runs_total);
        if !self.running.is_empty() {
            m.push_str(&format!(", running {}", self.running.join(" ")));
        }
        if !self.waiting.is_empty() {
            let held = self.waiting.join(" ");
            m.push_str(&format!(", waiting for {held} (another process has it)"));
        }
        m
    }
}

/// What was done: the count of runs per outcome; then the variants evaluated and the runs another
/// process had (a second `reproduce` on the same `--out`, or a `train` on the run: not failed,
/// and not run twice), where there were any. No newline at the end.
impl std::fmt::Display for ExecSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} runs already finished, {} started, {} resumed, {} failed",
            self.already_finished,
            self.started,
            self.resumed,
            self.failed.len()
        )?;
        if self.evaluated > 0 {
            let n = self.evaluated;
            write!(f, "\n{n} variant runs evaluated (docs/reproduce.md, \"Variants\")")?;
        }
        if !self.waited.is_empty() {
            write!(
                f,
                "\nwaited for {} runs another process had ({} finished there): {}",
                self.waited.len(),
                self.finished_elsewhere,
                self.waited.join(" ")
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_summary_says_each_outcome_and_only_the_extra_lines_that_apply() {
        let mut s = ExecSummary { already_finished: 2, started: 1, ..Default::default() };
        assert_eq!(s.to_string(), "2 runs already finished, 1 started, 0 resumed, 0 failed");
        s.evaluated = 3;
        s.waited = vec!["a/cpu/seed0".into(), "b/cpu/seed1".into()];
        s.finished_elsewhere = 1;
        let text = s.to_string();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 3, "{text}");
        assert_eq!(lines[1], "3 variant runs evaluated (docs/reproduce.md, \"Variants\")");
        assert_eq!(
            lines[2],
            "waited for 2 runs another process had (1 finished there): a/cpu/seed0 b/cpu/seed1"
        );
    }

    #[test]
    fn the_progress_message_names_the_data_or_the_runs() {
        let mut p = Progress {
            stage: Stage::Data("some_family".into()),
            runs_total: 4,
            runs_finished: 1,
            iterations_done: 0,
            iterations_total: 10,
            running: vec!["x".into()],
            waiting: vec![],
        };
        assert_eq!(p.message(), "collecting the some_family datasets");
        p.stage = Stage::Training;
        assert_eq!(p.message(), "runs 1/4 done, running x");
        p.waiting = vec!["y".into()];
        assert_eq!(p.message(), "runs 1/4 done, running x, waiting for y (another process has it)");
    }
}
