//! The results registry through the real binary, on a tiny point-robot experiment (seconds):
//! `results add` archives finished runs and refuses an unfinished one and one whose configuration
//! is not its cell's; `reproduce --report-only` from an empty directory (no run directories, no
//! data, no checkpoints) reports the archived runs exactly as the original tree reports them.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

#[path = "support/cli.rs"]
mod cli;

use cli::{check_fails, check_ok, promptdt_in};
use std::path::Path;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

const PROVENANCE: [&str; 10] = [
    "--commit",
    "abc1234",
    "--device-name",
    "test CPU",
    "--cpu",
    "test CPU",
    "--libtorch",
    "test",
    "--shared-with",
    "2",
];

/// `promptdt results add DIRS...` of manifest `m`'s smoke budget into `reg`, with the datasets'
/// cards under `data` and the fixed provenance.
fn add_args(m: &Path, reg: &Path, data: &Path, dirs: &[&Path]) -> Vec<String> {
    let mut a: Vec<String> = vec!["results".into(), "add".into()];
    a.extend(dirs.iter().map(|d| s(d).to_string()));
    for x in ["--exp", s(m), "--budget", "smoke", "--registry", s(reg), "--data-root", s(data)] {
        a.push(x.into());
    }
    a.extend(PROVENANCE.iter().map(|x| x.to_string()));
    a
}

#[test]
fn archived_runs_report_from_an_empty_directory_and_bad_runs_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let m = root.join("reg.toml");
    std::fs::write(&m, cli::tiny_manifest("reg", "Registry", "the results registry", 1)).unwrap();
    let tree = root.join("tree");
    let run = ["reproduce", s(&m), "--budget", "smoke", "--out", s(&tree), "--jobs", "2"];
    check_ok(&run, promptdt_in(root, &run));
    let reg = root.join("reg");
    let runs = tree.join("runs");
    let data = tree.join("data");
    let add = |dirs: &[&Path]| {
        let a = add_args(&m, &reg, &data, dirs);
        let out = promptdt_in(root, &a);
        (a, out)
    };

    // An unfinished run: its commit record one iteration short.
    let short = root.join("bad/runs/point_robot/prompt-dt/smoke/seed0");
    copy_dir(&runs.join("point_robot/prompt-dt/smoke/seed0"), &short);
    let latest = short.join("checkpoints/latest.json");
    let text = std::fs::read_to_string(&latest).unwrap();
    std::fs::write(&latest, text.replace("\"iteration\": 2", "\"iteration\": 1")).unwrap();
    let (a, out) = add(&[&short]);
    let err = check_fails(&a, out);
    assert!(err.contains("unfinished: 1 of 2 iterations"), "{err}");
    // A run whose configuration is not its cell's: named by key and value.
    std::fs::write(&latest, text).unwrap();
    let config = short.join("config.toml");
    let text = std::fs::read_to_string(&config).unwrap();
    assert!(text.contains("batch_size_per_task = 1"), "{text}");
    std::fs::write(&config, text.replace("batch_size_per_task = 1", "batch_size_per_task = 3"))
        .unwrap();
    let (a, out) = add(&[&short]);
    let err = check_fails(&a, out);
    assert!(err.contains("sampler.batch_size_per_task (3 vs 1)"), "{err}");
    assert!(!reg.join("point_robot/prompt-dt/smoke/seed0").exists());

    let good = [
        runs.join("point_robot/prompt-dt/smoke/seed0"),
        runs.join("point_robot/mt-orl/smoke/seed0"),
    ];
    let (a, out) = add(&[&good[0], &good[1]]);
    let stdout = check_ok(&a, out);
    assert!(stdout.contains("archived point_robot/mt-orl/smoke/seed0"), "{stdout}");
    let archived = reg.join("point_robot/prompt-dt/smoke/seed0");
    for f in ["config.toml", "run.json", "eval.jsonl", "metrics.jsonl", "task_stats.json"] {
        assert!(archived.join(f).is_file(), "{f}");
    }
    for f in ["normalisation.json", "provenance.json", "checkpoints/latest.json"] {
        assert!(archived.join(f).is_file(), "{f}");
    }
    // No weights, no datasets.
    let ckpts: Vec<_> = std::fs::read_dir(archived.join("checkpoints")).unwrap().collect();
    assert_eq!(ckpts.len(), 1);
    let prov = std::fs::read_to_string(archived.join("provenance.json")).unwrap();
    assert!(
        prov.contains("\"commit\": \"abc1234\"") && prov.contains("\"shared_with\": 2"),
        "{prov}"
    );

    // A fresh clone: nothing but the registry.
    let empty = root.join("empty");
    std::fs::create_dir(&empty).unwrap();
    let only = ["reproduce", s(&m), "--budget", "smoke", "--report-only", "--registry", s(&reg)];
    let stdout = check_ok(&only, promptdt_in(&empty, &only));
    assert!(stdout.contains("2 runs read from the registry"), "{stdout}");
    let cells =
        |dir: &Path| std::fs::read_to_string(dir.join("reports/reg-smoke/cells.csv")).unwrap();
    let fresh = cells(&empty.join("runs/repro"));
    assert_eq!(fresh, cells(&tree), "the archived runs report as the original tree");
    let report =
        std::fs::read_to_string(empty.join("runs/repro/reports/reg-smoke/report.md")).unwrap();
    assert!(!report.contains("What could not be read"), "{report}");
    assert!(!empty.join("runs/repro/data").exists() && !empty.join("runs/repro/runs").exists());
}

/// A budget planning more seeds than are archived: `--report-only` counts the seeds still to run
/// (the plan's), not only the archived ones (a registry holding only seed 0 once cut every cell
/// to 1 seed and called it finished).
#[test]
fn report_only_counts_the_planned_seeds_not_only_the_archived_ones() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let m = root.join("reg.toml");
    std::fs::write(&m, cli::tiny_manifest("reg", "Registry", "the results registry", 2)).unwrap();
    let tree = root.join("tree");
    let only = "point_robot/prompt-dt/smoke/seed0,point_robot/mt-orl/smoke/seed0";
    let run = ["reproduce", s(&m), "--budget", "smoke", "--out", s(&tree), "--only", only];
    check_ok(&run, promptdt_in(root, &run));
    let reg = root.join("reg");
    let runs = tree.join("runs");
    let dirs = ["point_robot/prompt-dt/smoke/seed0", "point_robot/mt-orl/smoke/seed0"]
        .map(|d| runs.join(d));
    let add = add_args(&m, &reg, &tree.join("data"), &[&dirs[0], &dirs[1]]);
    check_ok(&add, promptdt_in(root, &add));

    let empty = root.join("empty");
    std::fs::create_dir(&empty).unwrap();
    let only = ["reproduce", s(&m), "--budget", "smoke", "--report-only", "--registry", s(&reg)];
    check_ok(&only, promptdt_in(&empty, &only));
    let report =
        std::fs::read_to_string(empty.join("runs/repro/reports/reg-smoke/report.md")).unwrap();
    assert_eq!(report.matches("partial: 1 of 2 seeds finished").count(), 2, "{report}");

    // `--status`: each run's state and the command that goes on, nothing written.
    let latest = runs.join("point_robot/mt-orl/smoke/seed0/checkpoints/latest.json");
    let text = std::fs::read_to_string(&latest).unwrap();
    std::fs::write(&latest, text.replace("\"iteration\": 2", "\"iteration\": 1")).unwrap();
    let status = ["reproduce", s(&m), "--budget", "smoke", "--status", "--out", s(&tree)];
    let status = [&status[..], &["--registry", s(&reg)]].concat();
    let before = std::fs::read_dir(&tree).unwrap().count();
    let stdout = check_ok(&status, promptdt_in(root, &status));
    let line = |key: &str| stdout.lines().find(|l| l.starts_with(key)).unwrap_or("").to_string();
    assert!(line("point_robot/prompt-dt/smoke/seed0").ends_with("finished, archived"), "{stdout}");
    assert!(line("point_robot/prompt-dt/smoke/seed1").ends_with("not started"), "{stdout}");
    let partial = line("point_robot/mt-orl/smoke/seed0");
    assert!(partial.contains("at iteration 2 of 2 (resumes from 1); an archived copy"), "{stdout}");
    assert!(
        stdout.contains("4 runs of reg at the smoke budget: 2 done (2 archived in")
            && stdout.contains("0 part-way, 2 not started"),
        "{stdout}"
    );
    assert!(stdout.contains(&format!("--budget smoke --out {}", s(&tree))), "{stdout}");
    assert_eq!(std::fs::read_dir(&tree).unwrap().count(), before);
    // From a fresh clone: the archived runs, nothing else.
    let fresh = ["reproduce", s(&m), "--budget", "smoke", "--status", "--registry", s(&reg)];
    let stdout = check_ok(&fresh, promptdt_in(&empty, &fresh));
    let line = |key: &str| stdout.lines().find(|l| l.starts_with(key)).unwrap_or("").to_string();
    assert!(line("point_robot/mt-orl/smoke/seed0").ends_with("archived (no run directory here)"));
    assert!(stdout.contains("2 done (2 archived"), "{stdout}");
    let bad = [&fresh[..], &["--report-only"]].concat();
    cli::check_fails(&bad, promptdt_in(&empty, &bad));
}
