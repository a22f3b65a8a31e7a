//! The Python a test runs the environment worker with (`python -m promptdt.worker`, which needs the
//! `promptdt` package and gymnasium): `$PROMPTDT_PYTHON` when set, else the virtual environment
//! `make python` builds (`.venv-promptdt` in the checkout). Without one that imports both, the test
//! is skipped and the skip recorded like the reference data's ([`crate::reference`]); with
//! `PROMPTDT_REQUIRE_WORKER_PYTHON=1` (`make python-test`, which has just built one) it fails.

use std::panic::Location;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::reference::{append_skip, SKIP_LOG_VAR};

/// The interpreter to use (the same variable the library reads).
pub const PYTHON_VAR: &str = "PROMPTDT_PYTHON";
/// `1`: a worker Python must be found; its absence fails the test instead of skipping it.
pub const REQUIRE_VAR: &str = "PROMPTDT_REQUIRE_WORKER_PYTHON";

/// A Python that imports `promptdt.worker` and gymnasium, or `None` (the test is skipped).
#[track_caller]
pub fn worker_python() -> Option<PathBuf> {
    let caller = Location::caller();
    let candidate = match std::env::var_os(PYTHON_VAR).filter(|p| !p.is_empty()) {
        Some(p) => PathBuf::from(p),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../../.venv-promptdt/bin/python"),
    };
    let probe = Command::new(&candidate)
        .args(["-c", "import promptdt.worker, gymnasium"])
        .output()
        .map_err(|e| e.to_string())
        .and_then(|o| match o.status.success() {
            true => Ok(()),
            false => Err(String::from_utf8_lossy(&o.stderr).lines().last().unwrap_or("").into()),
        });
    let why = match probe {
        Ok(()) => return Some(candidate),
        Err(why) => why,
    };
    let test = format!("{}: {}", caller.file(), std::thread::current().name().unwrap_or("?"));
    let reason = format!(
        "no Python with promptdt and gymnasium at {} ({why}); set {PYTHON_VAR} or run `make python`",
        candidate.display()
    );
    if std::env::var(REQUIRE_VAR).as_deref() == Ok("1") {
        panic!("{test}: {reason}, and {REQUIRE_VAR}=1 requires one");
    }
    eprintln!("skipped: {reason}");
    if let Some(log) = std::env::var_os(SKIP_LOG_VAR).filter(|l| !l.is_empty()) {
        append_skip(Path::new(&log), &format!("{test} ({reason})"));
    }
    None
}
