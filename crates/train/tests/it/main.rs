//! The integration tests of `pdt-train`, one test binary: each `NAME.rs` here is a module (a test
//! file of its own before), run alone with `cargo test -p pdt-train --test it NAME::`. One binary a
//! crate, not one a file: linking test binaries (libtorch, MuJoCo) was most of the build. The
//! modules' tests are threads of one process: a test that seeds libtorch's generator or sets its
//! process-wide state takes `pdt_testkit::process::LIBTORCH`.

#[path = "support/golden.rs"]
mod golden;
#[path = "support/runs.rs"]
mod runs;

mod config_fuzz;
mod flat_optim;
mod macaw_run;
mod parity;
mod parity_bf16;
mod resume;
mod run_dir_fuzz;
