//! The integration tests of `pdt-train`, one test binary: each `NAME.rs` here is a module (a test
//! file of its own before), run alone with `cargo test -p pdt-train --test it NAME::`. One binary a
//! crate, not one a file: linking test binaries (libtorch, MuJoCo) was most of the build. The
//! modules' tests are threads of one process: a test that seeds libtorch's generator or sets its
//! process-wide state takes `pdt_testkit::process::LIBTORCH`.
//!
//! Kept a test binary of its own, where a fresh process is the point: `tests/step_reads.rs`
//! (libtorch's profiler sees every thread's operators).

#[path = "support/pack_fixture.rs"]
mod fixture;
#[path = "support/golden.rs"]
mod golden;
#[path = "support/runs.rs"]
mod runs;

mod config_fuzz;
mod flat_optim;
mod macaw_run;
mod pack_act;
mod pack_batched;
mod pack_flat;
mod pack_solo;
mod packs;
mod parity;
mod resume;
mod run_dir_fuzz;
