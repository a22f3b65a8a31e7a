//! The format is plain safetensors: `scripts/read_native_dataset.py` (numpy + the `safetensors`
//! package, nothing from promptdt) reads a file written here and gets the same episode returns.
//! Needs the project venv (`.venv/bin/python` at the workspace root); skipped with a note without
//! it, as on CI.

#![allow(clippy::unwrap_used)] // in tests a panic is the failure report

use crate::support;

use std::path::Path;
use std::process::Command;

use pdt_data::native::{write_task_dataset, FileMeta};
use support::sample_dataset;

#[test]
fn python_reader_prints_the_same_returns() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = root.join(".venv/bin/python");
    if !python.exists() {
        eprintln!("note: skipping: {} not found (no project venv)", python.display());
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cheetah_vel-2-prompt-expert.safetensors");
    let ds = sample_dataset(20, 6);
    write_task_dataset(&path, &ds, &FileMeta::new("cheetah_vel", 2, "prompt-expert")).unwrap();

    let out = Command::new(&python)
        .arg(root.join("scripts/read_native_dataset.py"))
        .arg(&path)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "script failed: {}\n{stdout}",
        String::from_utf8_lossy(&out.stderr)
    );

    let mut lines = stdout.lines();
    let header = lines.next().unwrap();
    for part in [
        "format=promptdt-trajectories",
        "version=1",
        "env=cheetah_vel",
        "task_index=2",
        "mode=prompt-expert",
        "steps=25",
        "episodes=4",
        "obs_dim=20",
        "act_dim=6",
    ] {
        assert!(header.contains(part), "{part:?} not in {header:?}");
    }
    let episodes: Vec<&str> = lines.collect();
    assert_eq!(episodes.len(), ds.trajectories.len(), "{stdout}");
    for (e, (line, t)) in episodes.iter().zip(&ds.trajectories).enumerate() {
        // "episode <e> steps <T> return <R> terminated <0|1> truncated <0|1>"
        let f: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(f.len(), 10, "{line}");
        assert_eq!(f[1].parse::<usize>().unwrap(), e);
        assert_eq!(f[3].parse::<usize>().unwrap(), t.len());
        let ret: f64 = f[5].parse().unwrap();
        // numpy sums pairwise, Rust sequentially: equal up to float64 rounding.
        let want = t.episode_return();
        assert!((ret - want).abs() <= 1e-9 * want.abs().max(1.0), "episode {e}: {ret} vs {want}");
        let last = t.len() - 1;
        assert_eq!(f[7], if t.terminated[last] { "1" } else { "0" }, "{line}");
        assert_eq!(f[9], if t.truncated[last] { "1" } else { "0" }, "{line}");
    }
}
