//! The integration tests of `pdt-testkit`, one test binary: each `NAME.rs` here is a module (a test
//! file of its own before), run alone with `cargo test -p pdt-testkit --test it NAME::`. One binary
//! a crate, not one a file: linking test binaries (libtorch, MuJoCo) was most of the build. The
//! modules' tests are threads of one process: a test that seeds libtorch's generator or sets its
//! process-wide state takes `pdt_testkit::process::LIBTORCH`.

mod architecture_doc;
mod one_build;
mod structure;
mod user_suites;
