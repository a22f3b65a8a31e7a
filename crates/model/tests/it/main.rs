//! The integration tests of `pdt-model`, one test binary: each `NAME.rs` here is a module (a test
//! file of its own before), run alone with `cargo test -p pdt-model --test it NAME::`. One binary a
//! crate, not one a file: linking test binaries (libtorch, MuJoCo) was most of the build. The
//! modules' tests are threads of one process: a test that seeds libtorch's generator or sets its
//! process-wide state takes `pdt_testkit::process::LIBTORCH`.
//!
//! libtorch's plumbing (the C++ shims, the profiler, the host allocator) is tested in `pdt-torch`.

#[path = "support/segments.rs"]
mod support;

mod act;
mod forward_options;
mod last_block;
