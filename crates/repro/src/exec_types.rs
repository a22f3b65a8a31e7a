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
