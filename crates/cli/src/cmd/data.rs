//! `promptdt data inspect | convert | report`.

use crate::args::{ConvertArgs, DataReportArgs, InspectArgs};
use anyhow::Result;

/// Per file: trajectories, steps, dims, dtypes, returns; a table or JSON.
pub fn inspect(a: &InspectArgs) -> Result<()> {
    let reports = pdt_data::inspect::inspect_path(&a.path)?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&reports)?);
    } else {
        out_inline!("{}", pdt_data::inspect::render_table(&reports));
    }
    Ok(())
}

/// The reference release's pickles into safetensors, one line per file.
pub fn convert(a: &ConvertArgs) -> Result<()> {
    let files = pdt_data::multitask::convert_reference_dir(&a.src, &a.dst)?;
    for f in &files {
        out!("{f}");
    }
    out!("converted {} files into {}", files.len(), a.dst.display());
    Ok(())
}

/// Our datasets beside the reference's: the tables, then the files written.
pub fn report(a: &DataReportArgs) -> Result<()> {
    let cfg = pdt_report::DatasetReportConfig {
        out_dir: a.out.clone().unwrap_or_else(|| a.ours.join("report")),
        ours: a.ours.clone(),
        reference: a.reference.clone(),
    };
    let summary = pdt_report::dataset_report(&cfg)?;
    for f in &summary.families {
        out_inline!("{}", f.markdown);
    }
    for w in &summary.warnings {
        eprintln!("warning: {w}");
    }
    for f in &summary.files {
        out!("wrote {}", f.display());
    }
    Ok(())
}
