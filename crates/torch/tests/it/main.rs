//! The integration tests of `pdt-torch`, one test binary: each `NAME.rs` here is a module, run
//! alone with `cargo test -p pdt-torch --test it NAME::`. The modules' tests are threads of one
//! process: a test that seeds libtorch's generator or sets its process-wide state takes
//! `pdt_testkit::process::LIBTORCH`.
//!
//! Kept a test binary of its own, where a fresh process is the point: `tests/host_memory.rs` (no
//! libtest harness: it measures the main thread's allocations).

mod bernoulli_cpu;
mod matmul;
mod profiler;
