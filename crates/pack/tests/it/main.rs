//! The integration tests of `pdt-pack`, one test binary: each `NAME.rs` here is a module, run
//! alone with `cargo test -p pdt-pack --test it NAME::`. The modules' tests are threads of one
//! process: a test that seeds libtorch's generator or trains takes `pdt_testkit::process::LIBTORCH`.
//!
//! Kept a test binary of its own, where a fresh process is the point: `tests/step_reads.rs`
//! (libtorch's profiler sees every thread's operators).

#[path = "support/pack_fixture.rs"]
mod fixture;
// The trainer's tiny runs, shared with `pdt-train`'s tests.
#[path = "../../../train/tests/it/support/runs.rs"]
mod runs;

mod pack_batched;
mod pack_flat;
mod pack_solo;
mod packs;
