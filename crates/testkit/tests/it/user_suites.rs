//! Issue 53's acceptance: a task suite goes through every front end without any of them naming it,
//! and adding one touches no Rust. The suites a user would write are the suite files under
//! `examples/` (the worked examples, and the toy suite the front ends' tests share); this checks
//! that no Rust source outside the tests names one, by its suite name or by its example's path.
//! That every front end takes such a suite is shown by running one through them all:
//! `crates/python/pytests/test_example_pendulum_tasks.py` (the README's commands: `promptdt
//! train`, `eval`, `report`, `serve`, and Python's `promptdt.evaluate`; `make python-test`).

use std::path::{Path, PathBuf};

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn files(dir: &Path, ext: &str, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    let mut entries: Vec<_> = entries.flatten().map(|e| e.path()).collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            files(&p, ext, out);
        } else if p.extension().is_some_and(|e| e == ext) {
            out.push(p);
        }
    }
}

/// The suite files under `examples/`: each `*.toml` with a `name` and `[[tasks]]` (what makes a
/// file a suite, `docs/your-own-tasks.md`), as (path from the root, suite name).
fn example_suites(root: &Path) -> Vec<(String, String)> {
    let mut tomls = Vec::new();
    files(&root.join("examples"), "toml", &mut tomls);
    let mut out = Vec::new();
    for path in tomls {
        let text = std::fs::read_to_string(&path).expect("example readable");
        let table: toml::Table =
            toml::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        if let (Some(name), Some(_)) =
            (table.get("name").and_then(|n| n.as_str()), table.get("tasks"))
        {
            let rel = path.strip_prefix(root).unwrap_or(&path).display().to_string();
            out.push((rel, name.to_string()));
        }
    }
    out
}

/// Whether `code` has `word` with no identifier character either side (`pendulum_mass`, not
/// `pendulum_mass_x`).
fn names(code: &str, word: &str) -> bool {
    let ident = |c: Option<char>| c.is_some_and(|c| c.is_ascii_alphanumeric() || c == '_');
    code.match_indices(word).any(|(i, _)| {
        !ident(code[..i].chars().next_back()) && !ident(code[i + word.len()..].chars().next())
    })
}

/// Every `.rs` file of the workspace that is not a test: each crate's `src/`, `build.rs`,
/// `examples/` and `benches/` (a crate's `tests/` may name the suites it tests).
fn non_test_sources(root: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut crates: Vec<PathBuf> = std::fs::read_dir(root.join("crates"))
        .expect("crates/ is readable")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("Cargo.toml").is_file())
        .collect();
    crates.sort();
    for dir in crates {
        for sub in ["src", "examples", "benches"] {
            files(&dir.join(sub), "rs", &mut out);
        }
        if dir.join("build.rs").is_file() {
            out.push(dir.join("build.rs"));
        }
    }
    out
}

#[test]
fn no_rust_source_names_a_user_suite() {
    let root = repo_root();
    let suites = example_suites(&root);
    // The worked example is one of them: an empty list would check nothing.
    assert!(
        suites
            .iter()
            .any(|(p, n)| p == "examples/pendulum_tasks/suite.toml" && n == "pendulum_mass"),
        "{suites:?}"
    );
    let sources = non_test_sources(&root);
    assert!(sources.len() > 100, "{} sources", sources.len());
    let mut named = Vec::new();
    for file in &sources {
        let code = std::fs::read_to_string(file).expect("source readable");
        for (path, name) in &suites {
            let dir = Path::new(path).parent().map(|d| d.display().to_string()).unwrap_or_default();
            if names(&code, name) || code.contains(&dir) {
                named.push(format!("{} names {name} ({path})", file.display()));
            }
        }
    }
    assert!(named.is_empty(), "a suite is a file, named by no Rust source:\n{}", named.join("\n"));
}

#[test]
fn the_name_matcher_finds_whole_names_only() {
    assert!(names("match env { \"pendulum_mass\" => 1 }", "pendulum_mass"));
    assert!(names("pendulum_mass", "pendulum_mass"));
    assert!(!names("pendulum_mass_2", "pendulum_mass"));
    assert!(!names("my_pendulum_mass", "pendulum_mass"));
}
