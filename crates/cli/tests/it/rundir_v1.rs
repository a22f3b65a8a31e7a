//! Run directories written by the code before `pdt-rundir` owned their files
//! (testdata/rundir-v1, its README says how they were made) through the binary of today:
//! `report` (with each method's loss column), `eval` (the same final evaluation, within the
//! measured cross-CPU bound: the fixture was made on another machine) and
//! `reproduce --report-only` (the same cells, the loss beside the returns).
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli as support;
use pdt_rundir::{FinalEval, RunDir};
use pdt_testkit::cpu::{json_close, CROSS_CPU_RETURN_REL};
use std::path::{Path, PathBuf};
use support::*;

fn fixture() -> PathBuf {
    repo("testdata/rundir-v1")
}

/// A copy of the fixture in `dir` (commands write into run directories), with the data its runs
/// were made from collected again (the collection is deterministic: `eval` checks their
/// fingerprints against `task_stats.json`).
fn copy(dir: &Path) -> PathBuf {
    let to = dir.join("rundir-v1");
    let st = std::process::Command::new("cp").arg("-a").arg(fixture()).arg(&to).status().unwrap();
    assert!(st.success());
    for (out, episodes) in [(dir.join("data"), "3"), (to.join("tree/data/point_robot-e2"), "2")] {
        let out = out.to_str().unwrap().to_string();
        ok(&[
            "collect",
            "--env",
            "point_robot",
            "--out",
            &out,
            "--episodes",
            episodes,
            "--prompt-episodes",
            "2",
        ]);
    }
    to
}

/// The `metrics.jsonl` column `column` of a run, by iteration.
fn loss_by_iteration(run: &Path, column: &str) -> Vec<(u64, f64)> {
    let lines = RunDir::open(run).unwrap().metrics().unwrap().unwrap().rows;
    lines.iter().map(|l| (l.iteration, l.get(column).unwrap())).collect()
}

#[test]
fn old_run_directories_are_reported_evaluated_and_reproduced() {
    let tmp = tempfile::tempdir().unwrap();
    let f = copy(tmp.path());

    // report: both runs, the MACAW one with its loss (train/policy_outer_loss).
    let report = tmp.path().join("report");
    ok(&["report", f.join("runs").to_str().unwrap(), "--out", report.to_str().unwrap()]);
    let table = std::fs::read_to_string(report.join("table.md")).unwrap();
    assert!(table.contains("macaw") && table.contains("prompt-dt"), "{table}");
    let runs = std::fs::read_to_string(report.join("runs.csv")).unwrap();
    let header: Vec<&str> = runs.lines().next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|c| *c == name).unwrap();
    for (method, column) in
        [("macaw", "train/policy_outer_loss"), ("prompt-dt", "train/action_loss")]
    {
        let row: Vec<&str> = runs
            .lines()
            .map(|l| l.split(',').collect::<Vec<_>>())
            .find(|r| r[col("method")] == method)
            .unwrap();
        assert_eq!(row[col("loss_metric")], column);
        let last = *loss_by_iteration(&f.join("runs").join(method), column).last().unwrap();
        assert_eq!(row[col("last_loss")].parse::<f64>().unwrap(), last.1, "{method}");
    }

    // eval: the same evaluation as the old code wrote (its eval_final.json says `split`).
    let data = tmp.path().join("data");
    for method in ["prompt-dt", "macaw"] {
        let run = f.join("runs").join(method);
        let before: FinalEval = RunDir::open(&run).unwrap().final_eval().unwrap().unwrap();
        let out = ok(&[
            "eval",
            "--run",
            run.to_str().unwrap(),
            "--episodes",
            "1",
            "--data",
            data.to_str().unwrap(),
        ]);
        assert!(out.contains("average (test)"), "{out}");
        let after = RunDir::open(&run).unwrap().final_eval().unwrap().unwrap();
        // The committed evaluation was made on another CPU (an AMD EPYC, AVX2): the same episodes,
        // lengths and tasks, returns within the measured cross-CPU bound, not bit for bit.
        let json = |e: &FinalEval| serde_json::to_value(e).unwrap();
        let close = json_close(&json(&after), &json(&before), CROSS_CPU_RETURN_REL);
        assert_eq!(close, Ok(()), "{method}: the evaluation now against the committed one");
    }

    // serve: the old run's policy loads (weights, statistics, its moved data's prompts).
    let run = f.join("runs/prompt-dt");
    let mut server = std::process::Command::new(env!("CARGO_BIN_EXE_promptdt"))
        .args(["serve", "--run", run.to_str().unwrap(), "--listen", "127.0.0.1:0", "--data"])
        .arg(&data)
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    let read = std::io::BufRead::read_line(
        &mut std::io::BufReader::new(server.stdout.take().unwrap()),
        &mut line,
    );
    let _ = server.kill();
    let _ = server.wait();
    read.unwrap();
    assert!(line.starts_with("listening on "), "{line}");

    // reproduce --report-only: the old version's cells, and the loss beside each curve point.
    let tree = f.join("tree");
    let manifest = f.join("tiny-repro.toml");
    ok(&[
        "reproduce",
        manifest.to_str().unwrap(),
        "--budget",
        "smoke",
        "--out",
        tree.to_str().unwrap(),
        "--report-only",
    ]);
    let old = fixture().join("tree/reports/rundir-v1-smoke");
    let new = tree.join("reports/rundir-v1-smoke");
    let read = |d: &Path, f: &str| std::fs::read_to_string(d.join(f)).unwrap();
    // The old version's cells, each line extended by the columns added since (appended at the
    // end, so a reader of the old columns reads the same values).
    let (old_cells, new_cells) = (read(&old, "cells.csv"), read(&new, "cells.csv"));
    assert_eq!(new_cells.lines().count(), old_cells.lines().count(), "{new_cells}");
    for (o, n) in old_cells.lines().zip(new_cells.lines()) {
        assert!(n.starts_with(&format!("{o},")), "{n} does not extend {o}");
    }
    let (old_curves, new_curves) = (read(&old, "curves.csv"), read(&new, "curves.csv"));
    assert_eq!(new_curves.lines().count(), old_curves.lines().count());
    for (o, n) in old_curves.lines().zip(new_curves.lines()).skip(1) {
        assert!(n.starts_with(&format!("{o},")), "{n} does not extend {o}");
        let cols: Vec<&str> = n.split(',').collect();
        let (cell, it) = (cols[0].trim_matches('"'), cols[1].parse::<u64>().unwrap());
        let column =
            if cell.ends_with("macaw") { "train/policy_outer_loss" } else { "train/action_loss" };
        assert_eq!(cols[4], column, "{n}");
        let run = tree.join("runs").join(cell).join("smoke/seed0");
        let want = loss_by_iteration(&run, column).into_iter().find(|(i, _)| *i == it).unwrap().1;
        assert_eq!(cols[5].parse::<f64>().unwrap(), want, "{n}");
    }
}
