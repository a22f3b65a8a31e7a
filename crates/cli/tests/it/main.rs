//! The integration tests of `promptdt`, one test binary: each `NAME.rs` here is a module (a test
//! file of its own before), run alone with `cargo test -p promptdt --test it NAME::`. One binary a
//! crate, not one a file: linking test binaries (libtorch, MuJoCo) was most of the build. The
//! modules' tests are threads of one process: a test that seeds libtorch's generator or sets its
//! process-wide state takes `pdt_testkit::process::LIBTORCH`.

#[path = "support/cli.rs"]
mod cli;
#[path = "../../../train/tests/it/support/golden.rs"]
mod golden;

mod adaptations;
mod cli_smoke;
mod collect_rl;
mod collect_suite;
mod families;
mod hardening;
mod hardening_data;
mod hardening_runs;
mod import_flat;
mod last_block;
mod macaw_cli;
mod packs;
mod prompt_strategies;
mod render_cli;
mod reproduce;
mod reproduce_trees;
mod reproduce_variants;
mod results;
mod rundir_v1;
mod serve_cli;
mod suites;
