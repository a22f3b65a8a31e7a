//! `promptdt bench` (training, inference and evaluation speed beside PyTorch) and `bench render`
//! (BENCHMARKS.md from the records).

use crate::bench_args::{BenchArgs, BenchCommand};
use anyhow::{Context, Result};
use std::path::Path;

/// Every file `bench` writes goes through the atomic writer: a killed benchmark leaves the old
/// file or the new one, never a torn one that `bench render` would then fail on.
fn write(path: &Path, text: &str) -> Result<()> {
    pdt_base::fs::write_atomic(path, text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

pub fn bench(a: &BenchArgs) -> Result<()> {
    if let Some(BenchCommand::Render(r)) = &a.action {
        let md = pdt_bench::record::render_dir(&r.records)?;
        write(&r.out, &md)?;
        out!("wrote {}", r.out.display());
        return Ok(());
    }
    let cfg = a.to_config()?;
    // A record is rendered into BENCHMARKS.md as the hardware's speed: emulated bf16 is not that.
    let emulated = cfg.matmul == pdt_base::device::Matmul::Bf16
        && pdt_torch::autocast::native(cfg.device).is_err();
    if let (Some(path), true) = (&a.json_out, emulated) {
        anyhow::bail!(
            "--matmul bf16 would run emulated here (no native bf16), and a record ({}) is read as \
             the hardware's speed: run it without --json-out",
            path.display()
        );
    }
    let report = pdt_bench::run(&cfg)?;
    let md = pdt_bench::render_markdown(&report);
    out_inline!("{md}");
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        write(&dir.join("bench.json"), &serde_json::to_string_pretty(&report)?)?;
        write(&dir.join("bench.md"), &md)?;
        out!("wrote {}/bench.json and bench.md", dir.display());
    }
    if let Some(path) = &a.json_out {
        let command = crate::bench_args::command_line();
        pdt_bench::record::from_report(&report, command, a.title.clone()).write(path)?;
        out!("wrote {}", path.display());
    }
    Ok(())
}
