//! The claim rule's bootstrap interval (crates/repro/src/stats.rs) against an independent
//! computation: `bootstrap_check.py` enumerates the exact stratified-bootstrap distribution of the
//! 3-vs-3 example (numpy, no random numbers), and the Rust interval, 10000 seeded draws, must land
//! within Monte Carlo error of its quantiles. Needs the project venv (`.venv/bin/python` with
//! numpy at the workspace root); skipped with a note without it.

use pdt_repro::stats::{self, bootstrap, cell_stats, example_scores, RESAMPLES, SEED};
use std::io::Write as _;
use std::path::Path;
use std::process::{Command, Stdio};

#[test]
fn the_bootstrap_interval_matches_an_exact_enumeration_in_numpy() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = root.join(".venv/bin/python");
    if !python.exists() {
        eprintln!("note: skipping: {} not found (no project venv)", python.display());
        return;
    }
    let (a, b) = example_scores();
    let input = serde_json::json!({ "a": a, "b": b }).to_string();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bootstrap_check.py");
    let mut child = Command::new(&python)
        .arg(&script)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{}: {e}", python.display()));
    child.stdin.take().unwrap().write_all(input.as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let exact: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let get = |k: &str| exact[k].as_f64().unwrap_or_else(|| panic!("{k} in {exact}"));

    let d = bootstrap(&a, Some(&b), RESAMPLES, SEED).unwrap();
    let ca = cell_stats(&a).unwrap();
    println!(
        "3 vs 3: Rust interval of a - b [{:.3}, {:.3}]; exact (numpy enumeration) [{:.3}, {:.3}]",
        d.lo,
        d.hi,
        get("diff_lo"),
        get("diff_hi")
    );
    // 10000 draws estimate a 2.5 % quantile with Monte Carlo error: half a normalised point is a
    // tolerance for it, and still a tenth of the interval's width, so a wrong scheme (tasks not
    // resampled, seeds not resampled, one side only) lands outside it.
    let tol = 0.5;
    assert!((d.lo - get("diff_lo")).abs() < tol, "{d:?} vs {exact}");
    assert!((d.hi - get("diff_hi")).abs() < tol, "{d:?} vs {exact}");
    assert!((ca.ci.lo - get("a_lo")).abs() < tol && (ca.ci.hi - get("a_hi")).abs() < tol);
    assert!((ca.sd.unwrap() - get("a_sd")).abs() < 1e-12, "{ca:?} vs {exact}");
    assert!((ca.iqm.unwrap() - get("a_iqm")).abs() < 1e-12, "{ca:?} vs {exact}");
    // And the verdicts the exact interval implies are the rule's.
    let margin_verdict = |m: f64| stats::judge_better(("a", &a), ("b", &b), m).unwrap().verdict;
    assert_eq!(margin_verdict(10.0), "holds");
    assert_eq!(margin_verdict(20.0), "undecided");
    assert_eq!(margin_verdict(30.0), "fails");
}
