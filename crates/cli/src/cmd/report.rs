//! `promptdt report`: the table and learning curves of run directories.

use crate::args::ReportArgs;
use anyhow::Result;

pub fn report(a: &ReportArgs) -> Result<()> {
    let cfg = pdt_report::ReportConfig {
        runs: a.runs.clone(),
        out_dir: a.out.clone(),
        title: a.title.clone(),
    };
    let summary = pdt_report::run(&cfg)?;
    out_inline!("{}", summary.markdown);
    for w in &summary.warnings {
        eprintln!("warning: {w}");
    }
    for f in &summary.files {
        out!("wrote {}", f.display());
    }
    Ok(())
}
