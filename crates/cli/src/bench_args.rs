//! `promptdt bench`'s arguments, and the benchmark configuration they become.

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use pdt_base::device::DeviceSpec;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Intra-op threads for both engines (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    #[arg(long, default_value_t = 30)]
    pub iters: usize,
    #[arg(long, default_value_t = 5)]
    pub warmup: usize,
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
    /// The model's products in `fp32`, `tf32` (CUDA) or `bf16` (mixed precision where the hardware
    /// has native bf16, or with PROMPTDT_BF16_EMULATED=1; also times fp32 in the same run).
    /// PyTorch's baseline gets the same (bf16: torch.autocast).
    #[arg(long, default_value = "fp32")]
    pub matmul: pdt_base::device::Matmul,
    /// Also count what one iteration of each case runs with libtorch's profiler: host operators
    /// and, on CUDA, kernels and copies, and where their time goes (not the evaluation cases).
    #[arg(long)]
    pub profile: bool,
    /// Comma-separated cases.
    #[arg(long, default_value = "train_b560,train_b64,infer_b1,infer_b50,eval_point_robot")]
    pub cases: String,
    /// Python with PyTorch 2.11 for the side-by-side baseline (omit to time promptdt alone).
    #[arg(long)]
    pub python: Option<PathBuf>,
    /// The PyTorch benchmark script.
    #[arg(long, default_value = "scripts/bench/bench_torch.py")]
    pub script: PathBuf,
    /// The PyTorch reference evaluation loop (for the `eval_point_robot` case).
    #[arg(long, default_value = "scripts/bench/bench_eval_torch.py")]
    pub eval_script: PathBuf,
    /// Episodes per task in `eval_point_robot`.
    #[arg(long, default_value_t = 50)]
    pub eval_episodes: usize,
    /// The PyTorch SAC / TD3 script (for `sac_h<H>_b<B>` and `td3_h<H>_b<B>` cases).
    #[arg(long, default_value = "scripts/bench/bench_rl_torch.py")]
    pub rl_script: PathBuf,
    /// The PyTorch MACAW script (for `macaw_w<W>_t<T>` cases: one meta-step of T tasks, width W).
    #[arg(long, default_value = "scripts/bench/bench_macaw_torch.py")]
    pub macaw_script: PathBuf,
    /// A trained run, served by the `serve_c<N>` cases (N concurrent episodes on loopback).
    #[arg(long)]
    pub serve_run: Option<PathBuf>,
    /// Steps per served episode in `serve_c<N>`.
    #[arg(long, default_value_t = 100)]
    pub serve_steps: usize,
    /// Episodes per client in `serve_c<N>`.
    #[arg(long, default_value_t = 2)]
    pub serve_episodes: usize,
    /// Directory for bench.json and bench.md.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Also write the run as a benchmark record (`benchmarks/*.json`: what, the command, the
    /// machine, the date, the commit and the numbers), from which `bench render` writes
    /// BENCHMARKS.md.
    #[arg(long)]
    pub json_out: Option<PathBuf>,
    /// The record's heading (default: the cases).
    #[arg(long, requires = "json_out")]
    pub title: Option<String>,
    #[command(subcommand)]
    pub action: Option<BenchCommand>,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Write BENCHMARKS.md from the benchmark records (`benchmarks/*.json`).
    Render(BenchRenderArgs),
}

#[derive(Debug, Args)]
pub struct BenchRenderArgs {
    #[arg(long, default_value = "benchmarks")]
    pub records: PathBuf,
    #[arg(long, default_value = "BENCHMARKS.md")]
    pub out: PathBuf,
}

/// The command line as typed, one shell word per argument (quoted where the shell would need it),
/// with the binary named `promptdt` wherever it was run from.
pub fn command_line() -> String {
    let quote = |a: String| {
        let plain = |c: char| c.is_ascii_alphanumeric() || "-_./=,:@+%".contains(c);
        if !a.is_empty() && a.chars().all(plain) {
            a
        } else {
            format!("'{}'", a.replace('\'', "'\\''"))
        }
    };
    let mut words = vec!["promptdt".to_string()];
    words.extend(std::env::args().skip(1).map(quote));
    words.join(" ")
}

impl BenchArgs {
    pub fn to_config(&self) -> Result<pdt_bench::BenchConfig> {
        let threads = self.threads.unwrap_or_else(pdt_base::threads::available_cores);
        if threads == 0 || self.iters == 0 {
            bail!("--threads and --iters must be at least 1");
        }
        let pytorch = self.python.as_ref().map(|python| pdt_bench::PyTorchBaseline {
            python: python.clone(),
            script: self.script.clone(),
        });
        if let Some(p) = &pytorch {
            if !p.script.is_file() {
                bail!("PyTorch benchmark script {} not found (run from the repository root or pass --script)", p.script.display());
            }
        }
        Ok(pdt_bench::BenchConfig {
            threads,
            iters: self.iters,
            warmup: self.warmup,
            device: pdt_torch::device::resolve(self.device)?,
            matmul: self.matmul,
            profile: self.profile,
            cases: self
                .cases
                .split(',')
                .map(|s| s.trim().to_string())
                .filter(|s| !s.is_empty())
                .collect(),
            pytorch_eval_script: pytorch.as_ref().map(|_| self.eval_script.clone()),
            pytorch_rl_script: pytorch.as_ref().map(|_| self.rl_script.clone()),
            pytorch_macaw_script: pytorch.as_ref().map(|_| self.macaw_script.clone()),
            serve_run: self.serve_run.clone(),
            serve_steps: self.serve_steps,
            serve_episodes: self.serve_episodes,
            pytorch,
            eval_episodes: self.eval_episodes.max(1),
        })
    }
}
