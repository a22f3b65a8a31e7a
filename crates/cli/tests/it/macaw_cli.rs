//! MACAW through the binary at a tiny budget: train (its data errors by name), eval with the run's
//! and with another adaptation, report, and the flags that only make sense for MACAW.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli as support;
use support::*;

const MACAW: &str = r#"
[macaw]
width = 8
buffer_skip = 1
inner_batch = 8
outer_batch = 8
task_batch = 3
adapt_batch = 4
adapt_steps = 2
"#;

#[test]
fn macaw_trains_evaluates_and_reports_from_the_cli() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny_setup(tmp.path());
    let (cfg_s, run) = (cfg.to_str().unwrap(), tmp.path().join("macaw"));
    let run_s = run.to_str().unwrap();
    // The official batches of 256 do not fit 3 episodes of 20 steps, every 7th kept.
    let err = fails(&["train", "--config", cfg_s, "--method", "macaw", "--out", run_s, "--quiet"]);
    assert!(err.contains("point_robot-") && err.contains("batch of 256"), "{err}");
    let small = tmp.path().join("macaw.toml");
    std::fs::write(&small, format!("{}\n{MACAW}", std::fs::read_to_string(&cfg).unwrap())).unwrap();
    let out = ok(&[
        "train",
        "--config",
        small.to_str().unwrap(),
        "--method",
        "macaw",
        "--out",
        run_s,
        "--quiet",
    ]);
    assert!(out.contains("held-out tasks after iteration 8"), "{out}");
    let config = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(config.contains("method = \"macaw\"") && config.contains("[macaw]"), "{config}");
    let eval = ok(&["eval", "--run", run_s, "--episodes", "1"]);
    assert!(eval.contains("adapted to each task with 2 steps on 4 transitions"), "{eval}");
    let eval = ok(&[
        "eval",
        "--run",
        run_s,
        "--episodes",
        "1",
        "--adapt-steps",
        "1",
        "--adapt-batch",
        "8",
    ]);
    assert!(eval.contains("1 steps on 8 transitions"), "{eval}");
    // The one flag family: `--adapt macaw` names MACAW's own adaptation; another is refused.
    let own = ["--adapt", "macaw", "--adapt-steps", "1", "--adapt-batch", "8"];
    let eval = ok(&[&["eval", "--run", run_s, "--episodes", "1"][..], &own[..]].concat());
    assert!(eval.contains("1 steps on 8 transitions"), "{eval}");
    let e = fails(&["eval", "--run", run_s, "--adapt", "finetune", "--adapt-steps", "1"]);
    assert!(e.contains("--adapt finetune") && e.contains("is macaw"), "{e}");
    let report = tmp.path().join("report");
    ok(&["report", run_s, "--out", report.to_str().unwrap()]);
    let table = std::fs::read_to_string(report.join("table.md")).unwrap();
    assert!(table.contains("macaw"), "{table}");

    // A preset replaces the [macaw] section; --resume takes no preset.
    let preset = tmp.path().join("preset");
    let e = fails(&[
        "train",
        "--config",
        small.to_str().unwrap(),
        "--method",
        "macaw",
        "--macaw-preset",
        "promptdt",
        "--out",
        preset.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(e.contains("batch of 256") || e.contains("transitions"), "{e}");
    let e = fails(&["train", "--resume", run_s, "--macaw-preset", "official"]);
    assert!(e.contains("--macaw-preset"), "{e}");
    // Prompt-DT runs have no adaptation to change.
    let pdt = tmp.path().join("pdt");
    ok(&[
        "train",
        "--config",
        cfg_s,
        "--out",
        pdt.to_str().unwrap(),
        "--iterations",
        "2",
        "--quiet",
    ]);
    let e = fails(&["eval", "--run", pdt.to_str().unwrap(), "--adapt-steps", "3"]);
    assert!(e.contains("--adapt-steps") && e.contains("prompt-dt"), "{e}");
}
