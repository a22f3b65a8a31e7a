//! `pdt-repro`: the paper's tables and figures, one command each (`promptdt reproduce`).
//!
//! - [`manifest`]: `experiments/*.toml`, one per paper artifact: cells, the paper's values, budgets.
//! - [`plan`]: a manifest at a budget expanded into ordinary run directories and configurations.
//! - [`exec`]: datasets, then every unfinished run as a `promptdt train` child process, `jobs` at a
//!   time, resuming killed runs; or one command per run for a scheduler (`--emit jobs`).
//! - [`variant`]: evaluation variants of a trained cell (a prompt strategy, an adaptation): its
//!   finished runs evaluated with an `[eval]` override, no training of their own.
//! - [`packs`]: `--pack N`, runs of one family grouped into packs, one process each.
//! - [`report`]: ours next to the paper, raw and normalised, with the paper's claims checked.
//! - [`registry`]: finished runs' small files committed in `results/` (`promptdt results add`),
//!   read by the report where a run directory is absent.
//! - [`render`]: `RESULTS.md` and the README's headline block from the registry.
//! - [`status`]: `--status`, where each run of a plan stands (finished, archived, part-way).
//! - [`sweep`]: runs at once, threads per run, runs per pack and their engine, by device.
//!
//! The library prints nothing; progress goes through a callback.

pub mod baselines;
pub mod exec;
pub mod exec_types;
pub mod manifest;
pub mod packs;
pub mod plan;
pub mod registry;
pub mod render;
pub mod report;
pub mod stats;
pub mod status;
pub mod suites;
pub mod sweep;
pub mod task_blind;
pub mod variant;
pub mod variant_spec;

pub use exec::{ExecOptions, ExecSummary, Progress, Stage};
pub use manifest::{Manifest, BUILTIN};
pub use plan::{Plan, PlanOptions, RunSpec, RunState};
pub use report::Report;
pub use sweep::{Sweep, SweepAsk, SweepDefaults};

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum ReproError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("experiment {origin}: {message}")]
    Manifest { origin: String, message: String },
    #[error("unknown experiment {name:?}: expected one of {known:?} or a manifest file")]
    UnknownExperiment { name: String, known: Vec<String> },
    #[error("experiment {experiment} has no budget {budget:?}; it has {known:?}")]
    UnknownBudget { experiment: String, budget: String, known: Vec<String> },
    #[error("no run {key:?} in this plan; runs: {known:?}")]
    UnknownRun { key: String, known: Vec<String> },
    #[error(
        "{dir} holds a run started from another configuration (differs in: {keys}); move it away \
         or use another --out"
    )]
    ConfigMismatch { dir: PathBuf, keys: String },
    #[error("{what} failed: {message}")]
    Child { what: String, message: String },
    #[error("{0}")]
    Invalid(String),
    /// A run directory's file cannot be read (the error names it).
    #[error(transparent)]
    RunDir(#[from] pdt_rundir::RunDirError),
}

/// One experiment of `promptdt reproduce --list` (and of the Python package's `experiments()`, as
/// JSON).
#[derive(Debug, Clone, serde::Serialize)]
pub struct ListEntry {
    pub name: String,
    pub title: String,
    pub cells: usize,
    pub pending: usize,
    pub budgets: Vec<BudgetCost>,
}

/// What an experiment costs at one budget.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BudgetCost {
    pub budget: String,
    pub runs: usize,
    /// The largest iteration count of a run.
    pub iterations: u64,
    /// Wall time, where the manifest states it.
    pub hours: Option<f64>,
    pub note: String,
}

/// The experiment's line, then one line per budget (runs, iterations, the wall time the manifest
/// states). No newline at the end.
impl std::fmt::Display for ListEntry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let pending =
            if self.pending > 0 { format!(", {} pending", self.pending) } else { String::new() };
        write!(f, "{:<30} {} ({} cells{pending})", self.name, self.title, self.cells)?;
        for b in &self.budgets {
            let h = b.hours.map_or(String::new(), |h| format!(", ~{h} h here"));
            let (budget, runs, iterations, note) = (&b.budget, b.runs, b.iterations, &b.note);
            write!(f, "\n    {budget:<6} {runs:>3} runs x {iterations} iterations{h}: {note}")?;
        }
        Ok(())
    }
}

/// Every committed experiment with its cost per budget.
pub fn list() -> Result<Vec<ListEntry>, ReproError> {
    let mut out = Vec::new();
    for (name, _) in BUILTIN {
        let m = Manifest::load(name)?;
        let mut budgets = Vec::new();
        for (b, budget) in &m.budgets {
            let o = plan::PlanOptions {
                budget: b.clone(),
                out: ".".into(),
                data_root: ".".into(),
                threads: 1,
                device: Default::default(),
                matmul: Default::default(),
                seeds: None,
            };
            let p = plan::plan(&m, &o)?;
            let iters = p.runs.iter().map(|r| r.config.train.iterations).max().unwrap_or(0);
            budgets.push(BudgetCost {
                budget: b.clone(),
                runs: p.runs.len(),
                iterations: iters,
                hours: budget.hours,
                note: budget.note.clone(),
            });
        }
        out.push(ListEntry {
            name: m.name.clone(),
            title: m.title.clone(),
            cells: m.cells.len(),
            pending: m.cells.iter().filter(|c| c.pending.is_some()).count(),
            budgets,
        });
    }
    Ok(out)
}
