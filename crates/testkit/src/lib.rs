//! `pdt-testkit`: helpers for the workspace's tests, written once. Only ever a dev-dependency; it is
//! not published and no library or binary links it.
//!
//! [`reference`]: where the reference release's data is (`../shared/data` beside the checkout, or
//! `PROMPTDT_REFERENCE_DATA`), and what a test does without it: skip, say so, and record the skip
//! for the `make test` notice; or fail, where `PROMPTDT_REQUIRE_REFERENCE_DATA=1` (CI).
//!
//! [`fs`]: a directory tree copied, and a file of the checkout found (`repo("testdata/..")`).
//!
//! [`golden`]: which golden fixture sets a parity test compares against, bit for bit or within
//! bounds (by the CPU the fixtures were made on).
//!
//! [`cpu`]: the CPU fingerprint that decides whether two float results can be compared bit for bit
//! (the parity fixtures record it), and whether batching changes a row's bits. Test-only: it lived
//! in `pdt_model`'s public API before, though no library code asks it.
//!
//! [`python`]: the Python that runs the environment worker (`promptdt.worker` with gymnasium), or
//! the test's skip, recorded as the reference data's are.
//!
//! [`process`]: one lock for libtorch's process-wide state, shared by the modules of a crate's one
//! integration-test binary.

pub mod cpu;
pub mod fs;
pub mod golden;
pub mod process;
pub mod python;
pub mod reference;
