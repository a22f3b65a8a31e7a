//! The integration tests of `pdt-repro`, one test binary: each `NAME.rs` here is a module (a test
//! file of its own before), run alone with `cargo test -p pdt-repro --test it NAME::`. One binary a
//! crate, not one a file: linking test binaries (libtorch, MuJoCo) was most of the build. The
//! modules' tests are threads of one process: a test that seeds libtorch's generator or sets its
//! process-wide state takes `pdt_testkit::process::LIBTORCH`.

mod bootstrap_python;
mod reference_experts;
mod results_md;
mod suites;
mod user_experiments;
