//! One module per subcommand: each turns its arguments into a validated library configuration,
//! makes one library call and prints the library's summary (its `Display`). `main` only parses and
//! dispatches here.

pub mod agent;
pub mod bench;
pub mod collect;
pub mod collect_rl;
pub mod data;
pub mod demo;
pub mod env;
pub mod eval;
pub mod model;
pub mod pack;
pub mod render;
pub mod report;
pub mod reproduce;
pub mod reproduce_jobs;
pub mod results;
pub mod serve;
pub mod train;

use indicatif::{ProgressBar, ProgressStyle};

/// A progress bar drawn with `template` (indicatif's syntax); `len` 0 until the library says.
pub fn bar(len: u64, template: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    if let Ok(style) = ProgressStyle::with_template(template) {
        pb.set_style(style.progress_chars("=> "));
    }
    pb
}

/// A bar that follows a library's `(done, total)` callback.
pub fn follow(pb: &ProgressBar) -> impl FnMut(usize, usize) + '_ {
    |done, total| {
        pb.set_length(total as u64);
        pb.set_position(done as u64);
    }
}
