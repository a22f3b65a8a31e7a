//! `pdt-report`: tables and learning-curve plots from run directories.
//!
//! The report reads only run directories (see `docs/run-directory.md`) and writes into one
//! output directory:
//!
//! - `table.md`, `table.csv`: final return on each test task and their average, per
//!   (environment, method), as mean ± std over seeds, like the paper's tables;
//! - `curves_<env>.png`, `curves_<env>.svg`, `curves.csv`: average test return against
//!   training iteration, one line per method with a ± std band, like the paper's Figure 2;
//! - `runs.csv`: which runs were found, which were used, and where each value came from;
//! - `offline.csv` (and a section of `table.md`): the held-out action error of runs evaluated
//!   offline (no environment), labelled as such and never among the returns.
//!
//! [`dataset_report`] does the same for a dataset directory written by `promptdt collect`:
//! episode return per task and mode against the reference release, with the quality bars
//! (`dataset_returns_<env>.{csv,md,png,svg}`).
//!
//! How the numbers are aggregated is documented in `docs/report.md`. Problems that do not
//! invalidate the report (a truncated last line, a run without evaluations) are returned in
//! [`ReportSummary::warnings`] and listed at the end of `table.md`; the library prints nothing.

mod aggregate;
mod datasets;
mod error;
mod load;
mod offline;
mod plot;
mod render;

use std::fs;
use std::path::{Path, PathBuf};

pub use aggregate::Stat;
pub use datasets::{
    dataset_report, BarStatus, DatasetReportConfig, DatasetReportSummary, FamilyReport, QualityBar,
    ReferenceReturn, ReturnStat, TaskMean, TaskRow,
};
pub use error::ReportError;

/// One line of a learning-curve figure drawn for another crate (the reproduction reports).
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend name.
    pub name: String,
    /// Grey line under the name in the legend (e.g. "3 seeds").
    pub sub: String,
    /// `(iteration, mean, std)`; non-finite points are left out.
    pub points: Vec<(f64, f64, f64)>,
}

/// A rendered figure: PNG bytes and SVG text.
#[derive(Debug, Clone)]
pub struct Figure {
    pub png: Vec<u8>,
    pub svg: String,
}

/// Learning curves (return against training iteration, ± std bands) in the style of the `report`
/// plots. `what` names the figure in errors.
pub fn learning_curves(
    caption: &str,
    y_desc: &str,
    series: &[Series],
    notes: &[String],
    what: &str,
) -> Result<Figure, ReportError> {
    let curves: Vec<plot::Curve> = series
        .iter()
        .enumerate()
        .map(|(i, s)| plot::Curve {
            name: s.name.clone(),
            color: plot::PALETTE[i % plot::PALETTE.len()],
            points: s
                .points
                .iter()
                .copied()
                .filter(|(x, m, d)| x.is_finite() && m.is_finite() && d.is_finite())
                .collect(),
        })
        .collect();
    let labels = plot::Labels {
        caption: caption.to_string(),
        x_desc: "Training iteration".to_string(),
        y_desc: y_desc.to_string(),
        legend_sub: series.iter().map(|s| s.sub.clone()).collect(),
        notes: notes.to_vec(),
    };
    let fig = plot::render_figure(&curves, &labels, plot::XAxis::Iterations, what, what)?;
    Ok(Figure { png: fig.png, svg: fig.svg })
}

/// Writes each `(file name, bytes)` into `out_dir` (created) atomically; returns the paths.
pub fn write_files(
    out_dir: &Path,
    outputs: &[(String, Vec<u8>)],
) -> Result<Vec<PathBuf>, ReportError> {
    write_outputs(out_dir, outputs)
}

/// What to report on and where to write it.
#[derive(Debug, Clone, Default)]
pub struct ReportConfig {
    /// Run directories, or parent directories that are searched recursively for `run.json`.
    pub runs: Vec<PathBuf>,
    /// Created if missing; existing report files in it are replaced.
    pub out_dir: PathBuf,
    /// Heading of `table.md` and prefix of plot titles.
    pub title: Option<String>,
}

/// What [`run`] produced.
#[derive(Debug, Clone)]
pub struct ReportSummary {
    /// Every file written, in the order written.
    pub files: Vec<PathBuf>,
    /// The content of `table.md`, for printing.
    pub markdown: String,
    /// Non-fatal problems, one sentence each, naming the file concerned.
    pub warnings: Vec<String>,
    /// Runs that contributed to the table and curves.
    pub runs_used: usize,
    /// Runs found but left out (no test evaluation); each has a warning.
    pub runs_skipped: usize,
}

/// Loads the runs, aggregates them and writes the report files into `cfg.out_dir`.
pub fn run(cfg: &ReportConfig) -> Result<ReportSummary, ReportError> {
    if cfg.runs.is_empty() {
        return Err(ReportError::NoInput);
    }
    let mut warnings = Vec::new();
    let dirs = load::discover(&cfg.runs)?;
    let runs =
        dirs.iter().map(|d| load::load_run(d, &mut warnings)).collect::<Result<Vec<_>, _>>()?;
    let agg = aggregate::aggregate(&runs, &mut warnings)?;

    let offline = offline::aggregate(&runs);

    let title = cfg.title.as_deref();
    let markdown = render::table_markdown(&agg, title, &warnings, &offline::markdown(&offline));
    // Render every figure before writing anything, so a plotting failure leaves the output
    // directory as it was rather than half-updated.
    let mut outputs: Vec<(String, Vec<u8>)> = vec![
        ("table.md".to_string(), markdown.clone().into_bytes()),
        ("table.csv".to_string(), render::table_csv(&agg).into_bytes()),
        ("curves.csv".to_string(), render::curves_csv(&agg).into_bytes()),
        ("runs.csv".to_string(), render::runs_csv(&agg).into_bytes()),
    ];
    if !offline.is_empty() {
        outputs.push(("offline.csv".to_string(), offline::csv(&offline).into_bytes()));
    }
    for env in agg.envs.iter().filter(|e| !e.curves.is_empty()) {
        let fig = plot::render(env, title)?;
        outputs.push((format!("curves_{}.png", env.file_stem), fig.png));
        outputs.push((format!("curves_{}.svg", env.file_stem), fig.svg.into_bytes()));
    }

    let files = write_outputs(&cfg.out_dir, &outputs)?;
    Ok(ReportSummary {
        files,
        markdown,
        warnings,
        runs_used: agg.runs_used,
        runs_skipped: agg.runs_skipped,
    })
}

/// Creates `out_dir` and writes each `(file name, bytes)` into it atomically; returns the paths.
/// Everything is rendered before this is called, so a failed report writes nothing half-made.
pub(crate) fn write_outputs(
    out_dir: &Path,
    outputs: &[(String, Vec<u8>)],
) -> Result<Vec<PathBuf>, ReportError> {
    fs::create_dir_all(out_dir).map_err(|e| ReportError::io(out_dir, e))?;
    let mut files = Vec::with_capacity(outputs.len());
    for (name, bytes) in outputs {
        let path = out_dir.join(name);
        write_atomic(&path, bytes)?;
        files.push(path);
    }
    Ok(files)
}

/// Writes via a temporary file in the same directory and a rename, so a reader (or a report
/// interrupted half-way) never sees a partially written file.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ReportError> {
    pdt_base::fs::write_atomic(path, bytes).map_err(|e| ReportError::io(path, e))
}
