//! The golden fixture sets a parity test compares against, and how: bit for bit where the fixtures
//! were made on a CPU with this machine's fingerprint, within measured cross-CPU bounds otherwise.
//! Shared by `crates/train/tests/parity.rs` and `crates/cli/tests/cli_smoke.rs` (via `#[path]`).
//!
//! Two sets:
//! - **committed** (`testdata/golden/`): made once, on an AVX-512 CPU; compared within [`bounds`].
//! - **live** (`$PROMPTDT_LIVE_GOLDEN`, written by `make test` with the PyTorch of
//!   `scripts/setup_torch_venv.sh` just before the tests run): made on this machine, so compared
//!   bit for bit. `.ci/run` sets `PROMPTDT_REQUIRE_LIVE_GOLDEN=1`, so CI cannot skip it.
#![allow(dead_code)] // each including test uses its part

use pdt_testkit::cpu::CpuFingerprint;
use std::path::{Path, PathBuf};

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
pub struct Golden {
    pub dir: PathBuf,
    pub label: &'static str,
    pub bitwise: bool,
}

impl Golden {
    pub fn file(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }
}

#[derive(serde::Deserialize)]
struct FixtureCpu {
    cpu: Option<CpuFingerprint>,
    torch_cpu_capability: String,
}

fn fixture_cpu(dir: &Path) -> FixtureCpu {
    let path = dir.join("prompt_dt_cpu.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!("{}: {e} (written by make_prompt_dt_fixtures.py)", path.display())
    });
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

pub fn committed_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../testdata/golden")
}

/// Every fixture set this run compares against: the committed one, and the live one when present
/// (required when `PROMPTDT_REQUIRE_LIVE_GOLDEN=1`).
pub fn sets() -> Vec<Golden> {
    let here = CpuFingerprint::detect();
    let dir = committed_dir();
    let made_on = fixture_cpu(&dir);
    let bitwise = made_on.cpu.is_some() && made_on.cpu == here;
    let mut sets = vec![Golden { dir, label: "committed", bitwise }];
    match std::env::var_os("PROMPTDT_LIVE_GOLDEN").map(PathBuf::from) {
        Some(dir) if dir.join("prompt_dt_cpu.json").is_file() => {
            let made_on = fixture_cpu(&dir);
            assert!(
                made_on.cpu.is_some() && made_on.cpu == here,
                "{}: live fixtures made on {:?} ({}), this machine is {:?}: remake them (make test)",
                dir.display(),
                made_on.cpu,
                made_on.torch_cpu_capability,
                here
            );
            sets.push(Golden { dir, label: "live", bitwise: true });
        }
        _ if std::env::var("PROMPTDT_REQUIRE_LIVE_GOLDEN").as_deref() == Ok("1") => panic!(
            "PROMPTDT_REQUIRE_LIVE_GOLDEN=1 but PROMPTDT_LIVE_GOLDEN names no fixture directory \
             (make test writes one when scripts/setup_torch_venv.sh has installed PyTorch)"
        ),
        _ => eprintln!(
            "live bitwise parity skipped: no PyTorch fixtures made on this machine \
             (bash scripts/setup_torch_venv.sh, then make test)"
        ),
    }
    for s in &sets {
        eprintln!(
            "golden set {}: {} ({})",
            s.label,
            s.dir.display(),
            if s.bitwise { "bit for bit" } else { "within the cross-CPU bounds" }
        );
    }
    sets
}
