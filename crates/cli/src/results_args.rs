//! The `results` subcommand's arguments (the results registry), apart from `args.rs` to keep each
//! file readable.

use clap::{Args, Subcommand};
use std::path::PathBuf;

#[derive(Debug, Subcommand)]
pub enum ResultsCommand {
    /// Archive finished runs of an experiment (their small files and provenance) into the registry.
    Add(Box<ResultsAddArgs>),
    /// Write RESULTS.md and the README's headline block from the registry.
    Render(ResultsRenderArgs),
}

#[derive(Debug, Args)]
pub struct ResultsAddArgs {
    /// Run directories as `reproduce` lays them out (`.../<cell id>/<budget>/seed<N>`).
    #[arg(required = true)]
    pub runs: Vec<PathBuf>,
    /// The experiment the runs belong to (fig2, table1, ... or a manifest file).
    #[arg(long)]
    pub exp: String,
    #[arg(long)]
    pub budget: String,
    /// Where the runs' datasets (their `dataset.json` cards) are (default: where each run's
    /// config.toml says).
    #[arg(long)]
    pub data_root: Option<PathBuf>,
    #[arg(long, default_value = "results")]
    pub registry: PathBuf,
    /// The commit of the binary that trained the runs.
    #[arg(long)]
    pub commit: String,
    /// The GPU (or CPU) model that ran them.
    #[arg(long)]
    pub device_name: String,
    /// The machine's CPU model.
    #[arg(long)]
    pub cpu: String,
    /// The libtorch build they ran with.
    #[arg(long)]
    pub libtorch: String,
    /// `solo` (one run per process) or `packed`.
    #[arg(long, default_value = "solo", value_parser = ["solo", "packed"])]
    pub packing: String,
    /// How many runs shared the device at once, these included.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    pub shared_with: u32,
    /// When they ran, YYYY-MM-DD (default: the day run.json says each was created).
    #[arg(long)]
    pub date: Option<String>,
    #[arg(long, default_value = "")]
    pub note: String,
}

impl ResultsAddArgs {
    pub fn to_options(&self) -> pdt_repro::registry::AddOptions {
        pdt_repro::registry::AddOptions {
            runs: self.runs.clone(),
            experiment: self.exp.clone(),
            budget: self.budget.clone(),
            data_root: self.data_root.clone(),
            registry: self.registry.clone(),
            provenance: pdt_repro::registry::ProvenanceFlags {
                commit: self.commit.clone(),
                device_name: self.device_name.clone(),
                cpu: self.cpu.clone(),
                libtorch: self.libtorch.clone(),
                packing: self.packing.clone(),
                shared_with: self.shared_with,
                date: self.date.clone(),
                note: self.note.clone(),
            },
        }
    }
}

#[derive(Debug, Args)]
pub struct ResultsRenderArgs {
    #[arg(long, default_value = "results")]
    pub registry: PathBuf,
    #[arg(long, default_value = "RESULTS.md")]
    pub out: PathBuf,
    /// The README whose `<!-- results:begin -->` block is rewritten.
    #[arg(long, default_value = "README.md")]
    pub readme: PathBuf,
    /// Leave the README (and docs/prompt-control.md's generated table beside it) alone.
    #[arg(long)]
    pub no_readme: bool,
}

impl ResultsRenderArgs {
    pub fn to_options(&self) -> pdt_repro::render::RenderOptions {
        pdt_repro::render::RenderOptions {
            registry: self.registry.clone(),
            results_md: self.out.clone(),
            readme: (!self.no_readme).then(|| self.readme.clone()),
            // Beside the README: the checkout's docs/prompt-control.md, whose table is generated.
            prompt_control_doc: (!self.no_readme)
                .then(|| self.readme.with_file_name("docs").join("prompt-control.md")),
        }
    }
}
