//! The golden fixture sets a parity test compares against, and how: bit for bit where the fixtures
//! were made on a CPU with this machine's fingerprint, within measured cross-CPU bounds otherwise.
//! Shared by `crates/train/tests/it/parity.rs` and `crates/cli/tests/it/cli_smoke.rs` (via `#[path]`).
//! Which sets, and whether bit for bit, is `pdt_testkit::golden` (MACAW's parity test chooses the
//! same way); the Prompt-DT [`bounds`] are here.
#![allow(dead_code)] // each including test uses its part

/// Cross-CPU bounds, each 5-20x the largest difference measured between the committed fixtures
/// (AVX-512) and the same script run on an AVX2 CPU (`scripts/golden/compare_fixtures.py`; table in
/// testdata/golden/README.md, "Across CPUs").
pub mod bounds {
    /// Action predictions, absolute (measured 2.09e-7; actions are in (-1, 1)).
    pub const ACTION_ABS: f64 = 1e-6;
    /// Loss and gradient norm, relative (measured: identical).
    pub const SCALAR_REL: f64 = 1e-6;
    /// Each gradient tensor: max |ours - theirs| / max |theirs| (measured 4.64e-7).
    pub const GRAD_REL_TO_MAX: f64 = 1e-5;
    /// Parameters after two AdamW steps, absolute (measured 1.86e-9, one f32 ulp at 0.02). The two
    /// steps (lr 1e-8 and 2e-8) move a parameter by up to ~3e-8, so a wrong sign or a step off by a
    /// third still fails.
    pub const PARAM_ABS: f64 = 1e-8;
}

/// One directory of fixtures and whether this machine must match it bit for bit.
#[allow(unused_imports)] // each including test uses its part
pub use pdt_testkit::golden::{committed_dir, GoldenSet as Golden};

/// Every Prompt-DT fixture set this run compares against (`pdt_testkit::golden::sets`): the
/// committed one, and the live one when present (required when `PROMPTDT_REQUIRE_LIVE_GOLDEN=1`).
pub fn sets() -> Vec<Golden> {
    pdt_testkit::golden::sets("prompt_dt_cpu.json")
}
