//! The integration tests of `pdt-data`, one test binary: each `NAME.rs` here is a module (a test
//! file of its own before), run alone with `cargo test -p pdt-data --test it NAME::`. One binary a
//! crate, not one a file: linking test binaries (libtorch, MuJoCo) was most of the build. The
//! modules' tests are threads of one process: a test that seeds libtorch's generator or sets its
//! process-wide state takes `pdt_testkit::process::LIBTORCH`.

mod support;

mod card_fuzz;
mod flat;
mod flat_hdf5;
mod native_atomic;
mod native_multitask;
mod native_python;
mod native_roundtrip;
mod native_validation;
mod pickle_official;
mod pickle_robustness;
mod pickle_variants;
