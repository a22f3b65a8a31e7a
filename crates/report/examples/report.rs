//! Runs the report without the full CLI (which needs libtorch):
//! `cargo run -p pdt-report --example report -- OUT_DIR RUN_OR_PARENT_DIR...`

use std::path::PathBuf;
use std::process::ExitCode;

fn main() -> ExitCode {
    let mut args = std::env::args_os().skip(1).map(PathBuf::from);
    let Some(out_dir) = args.next() else {
        eprintln!("usage: report OUT_DIR RUN_OR_PARENT_DIR...");
        return ExitCode::from(2);
    };
    let cfg = pdt_report::ReportConfig { runs: args.collect(), out_dir, title: None };
    match pdt_report::run(&cfg) {
        Ok(summary) => {
            for w in &summary.warnings {
                eprintln!("warning: {w}");
            }
            print!("{}", summary.markdown);
            for f in &summary.files {
                eprintln!("wrote {}", f.display());
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
