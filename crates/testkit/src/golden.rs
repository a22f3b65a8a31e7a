//! Which golden fixture sets a parity test compares against, and how: bit for bit against fixtures
//! made on this machine in this run's environment (the live set), within the test's measured
//! cross-CPU bounds against the committed ones. The Prompt-DT parity tests (`prompt_dt_cpu.json`)
//! and the MACAW ones (`macaw_cpu.json`) choose the same way.
//!
//! Two sets:
//! - **committed** (`testdata/golden/`): made once, on another machine (Prompt-DT's on an AVX-512
//!   CPU, MACAW's on an AMD EPYC with AVX2). Never compared bit for bit, even on a CPU with the
//!   same fingerprint: the fingerprint does not see everything that picks a kernel
//!   (`ATEN_CPU_CAPABILITY`, `MKL_CBWR`, `ONEDNN_MAX_CPU_ISA`, a microcode or hypervisor that hides
//!   a flag), so "a CPU like the one that made them" is a guess, and a wrong guess fails a user's
//!   `make test`. `scripts/test_other_kernels.sh` checks that on any CPU.
//! - **live** (`$PROMPTDT_LIVE_GOLDEN`, written by `make test` with the PyTorch of
//!   `scripts/setup_torch_venv.sh` just before the tests run): made on this machine, so compared
//!   bit for bit. `.ci/run` sets `PROMPTDT_REQUIRE_LIVE_GOLDEN=1`, so CI cannot skip it.

use std::path::{Path, PathBuf};

use crate::cpu::CpuFingerprint;

/// Directory of live fixtures (made on this machine by `make test`).
pub const LIVE_VAR: &str = "PROMPTDT_LIVE_GOLDEN";
/// `1`: a missing live fixture set fails the test instead of skipping its bitwise part (CI).
pub const REQUIRE_LIVE_VAR: &str = "PROMPTDT_REQUIRE_LIVE_GOLDEN";

/// One directory of fixtures and whether this machine must match it bit for bit.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GoldenSet {
    pub dir: PathBuf,
    /// `committed` or `live`.
    pub label: &'static str,
    pub bitwise: bool,
}

impl GoldenSet {
    pub fn file(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }
}

/// The fixtures committed in the repository (`testdata/golden/`).
pub fn committed_dir() -> PathBuf {
    crate::fs::repo("testdata/golden")
}

/// What a fixture set's CPU record (`prompt_dt_cpu.json`, `macaw_cpu.json`) says.
#[derive(Debug, Clone, serde::Deserialize)]
pub struct FixtureCpu {
    /// The fingerprint of the CPU the fixtures were made on; `None` where it was not recorded.
    pub cpu: Option<CpuFingerprint>,
    /// torch's `get_cpu_capability()` there (for messages).
    #[serde(default)]
    pub torch_cpu_capability: String,
}

/// Reads `dir/cpu_file`; panics (the test fails) where it is missing or unreadable.
pub fn fixture_cpu(dir: &Path, cpu_file: &str) -> FixtureCpu {
    let path = dir.join(cpu_file);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!("{}: {e} (written with the fixtures by scripts/golden/)", path.display())
    });
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Every fixture set this run compares against, by the CPU record `cpu_file` beside the fixtures:
/// the committed one (within bounds: made on another machine), and the live one when present (it
/// must have been made here; required when `PROMPTDT_REQUIRE_LIVE_GOLDEN=1`).
pub fn sets(cpu_file: &str) -> Vec<GoldenSet> {
    let here = CpuFingerprint::detect();
    let dir = committed_dir();
    // Read for its errors (a missing record fails the test); the committed set is never bitwise.
    let _made_on = fixture_cpu(&dir, cpu_file);
    let mut sets = vec![GoldenSet { dir, label: "committed", bitwise: false }];
    match std::env::var_os(LIVE_VAR).map(PathBuf::from) {
        Some(dir) if dir.join(cpu_file).is_file() => {
            let made_on = fixture_cpu(&dir, cpu_file);
            assert!(
                made_on.cpu.is_some() && made_on.cpu == here,
                "{}: live fixtures made on {:?} ({}), this machine is {:?}: remake them (make test)",
                dir.display(),
                made_on.cpu,
                made_on.torch_cpu_capability,
                here
            );
            sets.push(GoldenSet { dir, label: "live", bitwise: true });
        }
        _ if std::env::var(REQUIRE_LIVE_VAR).as_deref() == Ok("1") => panic!(
            "{REQUIRE_LIVE_VAR}=1 but {LIVE_VAR} names no directory with {cpu_file} (make test \
             writes one when scripts/setup_torch_venv.sh has installed PyTorch)"
        ),
        _ => eprintln!(
            "live bitwise parity ({cpu_file}) skipped: no PyTorch fixtures made on this machine \
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn committed_sets_are_never_bitwise() {
        for file in ["prompt_dt_cpu.json", "macaw_cpu.json"] {
            let sets = sets(file);
            assert_eq!(sets[0].label, "committed");
            assert_eq!(sets[0].file("x"), committed_dir().join("x"));
            // Even where the record names this very CPU (MACAW's were made on an AMD EPYC).
            assert!(!sets[0].bitwise, "{file}");
        }
        assert!(fixture_cpu(&committed_dir(), "macaw_cpu.json").cpu.is_some());
    }
}
