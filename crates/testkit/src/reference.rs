//! The reference release's data (the Prompt-DT authors' prompt files and task parameters;
//! `shared/data/README.md` in the project's CI). A user's clone does not have it, so every test
//! that reads it asks here first:
//!
//! - the directory is `$PROMPTDT_REFERENCE_DATA` when set, else `../shared/data` beside the
//!   checkout (where CI puts it);
//! - when it is there, the test gets the path it asked for;
//! - when it is not, the test is skipped: one line on stderr (libtest shows it only with
//!   `--nocapture`), and one line appended to `$PROMPTDT_REFERENCE_SKIP_LOG` when set, which
//!   `make test` sets and then prints once, after the run, with the reason;
//! - but with `PROMPTDT_REQUIRE_REFERENCE_DATA=1` (set by `.ci/run`) a missing directory is a test
//!   failure, so CI, which has the data, can never skip these tests silently.

use std::io::Write as _;
use std::panic::Location;
use std::path::{Path, PathBuf};

/// Points at the reference data directory (the one holding `official-prompts/`).
pub const DATA_VAR: &str = "PROMPTDT_REFERENCE_DATA";
/// `1`: the reference data must be present; its absence fails the test instead of skipping it.
pub const REQUIRE_VAR: &str = "PROMPTDT_REQUIRE_REFERENCE_DATA";
/// A file to which each skipped test appends one line (`make test` sets it and prints it).
pub const SKIP_LOG_VAR: &str = "PROMPTDT_REFERENCE_SKIP_LOG";

/// The workspace root (this crate is `crates/testkit`), without `..` where it can be resolved, so
/// the messages name a plain path.
fn workspace_root() -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    std::fs::canonicalize(&root).unwrap_or(root)
}

/// Where the reference data should be: `$PROMPTDT_REFERENCE_DATA`, else `../shared/data` beside
/// the checkout. Whether it is there is not checked.
pub fn data_dir() -> PathBuf {
    match std::env::var_os(DATA_VAR) {
        Some(d) if !d.is_empty() => PathBuf::from(d),
        _ => {
            let root = workspace_root();
            match root.parent() {
                Some(beside) => beside.join("shared/data"),
                None => root.join("../shared/data"),
            }
        }
    }
}

/// The reference release's 42 prompt files (`official-prompts/`), or `None` (test skipped).
#[track_caller]
pub fn official_prompts() -> Option<PathBuf> {
    require(data_dir().join("official-prompts"), Location::caller())
}

/// One file of `official-prompts/` (e.g. `cheetah_vel-2-prompt-expert.pkl`), or `None`.
#[track_caller]
pub fn official_prompt(name: &str) -> Option<PathBuf> {
    require(data_dir().join("official-prompts").join(name), Location::caller())
}

/// `official-task-parameters.json`, or `None`.
#[track_caller]
pub fn task_parameters() -> Option<PathBuf> {
    require(data_dir().join("official-task-parameters.json"), Location::caller())
}

/// `path` if it exists; otherwise fails (when required) or records the skip and returns `None`.
fn require(path: PathBuf, caller: &Location<'_>) -> Option<PathBuf> {
    // libtest names each test's thread after the test; the caller's file says which binary.
    let thread = std::thread::current();
    let test = format!("{}: {}", caller.file(), thread.name().unwrap_or("?"));
    let required = std::env::var(REQUIRE_VAR).as_deref() == Ok("1");
    let log = std::env::var_os(SKIP_LOG_VAR).filter(|l| !l.is_empty()).map(PathBuf::from);
    decide(path, &test, required, log.as_deref())
}

/// [`require`] with its environment read: unit-testable without changing the process's variables.
fn decide(path: PathBuf, test: &str, required: bool, log: Option<&Path>) -> Option<PathBuf> {
    if path.exists() {
        return Some(path);
    }
    if required {
        panic!(
            "{test}: {} not found, and {REQUIRE_VAR}=1 requires the reference release's data \
             (put it at ../shared/data beside the checkout or set {DATA_VAR})",
            path.display()
        );
    }
    eprintln!("skipped: {} not found (reference release's data; see {DATA_VAR})", path.display());
    if let Some(log) = log {
        append_skip(log, test);
    }
    None
}

/// Appends `line` to the skip log `log`.
pub(crate) fn append_skip(log: &Path, line: &str) {
    // One short line per write with O_APPEND: test binaries running side by side do not
    // interleave their lines. A log that cannot be written must not fail the test it reports.
    let line = format!("{line}\n");
    let written = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(log)
        .and_then(|mut f| f.write_all(line.as_bytes()));
    if let Err(e) = written {
        eprintln!("{}: {e}", log.display());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_present_path_is_returned_and_nothing_is_logged() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let log = tmp.path().join("skipped.txt");
        let got = decide(tmp.path().to_path_buf(), "t", true, Some(&log));
        assert_eq!(got.as_deref(), Some(tmp.path()));
        assert!(!log.exists());
    }

    #[test]
    fn a_missing_path_is_skipped_and_each_skip_logged_on_one_line() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let log = tmp.path().join("skipped.txt");
        let missing = tmp.path().join("official-prompts");
        assert_eq!(decide(missing.clone(), "a.rs: one", false, Some(&log)), None);
        assert_eq!(decide(missing, "b.rs: two", false, Some(&log)), None);
        let text = std::fs::read_to_string(&log).expect("log written");
        assert_eq!(text, "a.rs: one\nb.rs: two\n");
    }

    #[test]
    #[should_panic(expected = "PROMPTDT_REQUIRE_REFERENCE_DATA=1 requires")]
    fn a_missing_path_fails_when_required() {
        let tmp = tempfile::tempdir().expect("tempdir");
        decide(tmp.path().join("official-prompts"), "t", true, None);
    }

    #[test]
    fn the_default_is_beside_the_workspace_root() {
        // `../shared/data` is relative to the checkout: the root must be the workspace's.
        let manifest = std::fs::read_to_string(workspace_root().join("Cargo.toml")).expect("root");
        assert!(manifest.contains("[workspace]") && manifest.contains("crates/testkit"));
        if std::env::var_os(DATA_VAR).is_none() {
            let beside = workspace_root().parent().map(|p| p.join("shared/data"));
            assert_eq!(Some(data_dir()), beside);
        }
    }
}
