//! A run killed and resumed produces exactly the losses and evaluations of an uninterrupted run.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::runs;

use pdt_rundir::config::{Method, TrainConfig};
use pdt_train::run::{train, TrainOptions, TrainSummary};
use runs::{lines, tiny_data};
use std::path::Path;

/// A run that must succeed.
fn run(cfg: Option<TrainConfig>, dir: &Path, resume: bool, stop: Option<u64>) -> TrainSummary {
    runs::run(cfg, dir, resume, stop).unwrap()
}

#[test]
fn killed_and_resumed_run_equals_uninterrupted_run() {
    let _torch = pdt_testkit::process::libtorch(); // trains: seeds and draws from the process's generator
    let (tmp, data) = tiny_data();
    for method in [Method::PromptDt, Method::MtBcFinetune] {
        let (full, cut) = (
            tmp.path().join(format!("full-{method:?}")),
            tmp.path().join(format!("cut-{method:?}")),
        );
        assert!(run(Some(runs::tiny_config(&data, method)), &full, false, None).finished);
        // Interrupted after iteration 3: the last checkpoint is iteration 2, and iteration 3's
        // metrics line (written after the checkpoint) must be discarded on resume.
        let stopped = run(Some(runs::tiny_config(&data, method)), &cut, false, Some(3));
        assert!(!stopped.finished);
        assert_eq!(lines(&cut.join("metrics.jsonl")).len(), 3);
        let resumed = run(None, &cut, true, None);
        assert!(resumed.finished);
        let (a, b) = (lines(&full.join("metrics.jsonl")), lines(&cut.join("metrics.jsonl")));
        assert_eq!(a.len(), 6);
        assert_eq!(a, b, "{method:?}: training losses differ after resume");
        // The training time carries over the resume: it never goes back.
        let elapsed: Vec<f64> = std::fs::read_to_string(cut.join("metrics.jsonl"))
            .unwrap()
            .lines()
            .map(|l| {
                serde_json::from_str::<serde_json::Value>(l).unwrap()["time/elapsed_s"]
                    .as_f64()
                    .unwrap()
            })
            .collect();
        assert!(elapsed.windows(2).all(|w| w[0] <= w[1]), "{method:?}: elapsed {elapsed:?}");
        assert_eq!(
            lines(&full.join("eval.jsonl")),
            lines(&cut.join("eval.jsonl")),
            "{method:?}: evaluations differ"
        );
        let (ca, cb) = (
            std::fs::read_to_string(full.join("metrics.csv")).unwrap(),
            std::fs::read_to_string(cut.join("metrics.csv")).unwrap(),
        );
        assert_eq!(ca.lines().count(), cb.lines().count());
        let w = |d: &Path| std::fs::read(d.join("checkpoints/step_12.safetensors")).unwrap();
        assert!(w(&full) == w(&cut), "{method:?}: final weights differ");
        // resuming a finished run is a no-op that reports it finished
        assert!(run(None, &cut, true, None).finished);
    }
}

#[test]
fn starting_over_an_existing_run_is_refused() {
    let _torch = pdt_testkit::process::libtorch(); // trains: seeds and draws from the process's generator
    let (tmp, data) = tiny_data();
    let mut cfg = runs::tiny_config(&data, Method::MtOrl);
    cfg.train.iterations = 2;
    let dir = tmp.path().join("run");
    run(Some(cfg.clone()), &dir, false, None);
    let mut progress = |_: &pdt_train::run::Progress| {};
    let err = train(
        Some(cfg),
        &dir,
        TrainOptions {
            resume: false,
            resume_with: Default::default(),
            stop_after_iterations: None,
            progress: &mut progress,
            interrupt: Default::default(),
            envs: None,
        },
    )
    .unwrap_err();
    assert!(err.to_string().contains("--resume"), "{err}");
}

/// Resume points between checkpoints (`train.resume_interval`): a run stopped just after one
/// resumes from it, ends byte-identical to a run without them, and keeps only the checkpoints'
/// weights.
#[test]
fn resume_points_between_checkpoints_lose_nothing_and_leave_no_files() {
    let _torch = pdt_testkit::process::libtorch(); // trains: seeds and draws from the process's generator
    let (tmp, data) = tiny_data();
    let mut plain = runs::tiny_config(&data, Method::PromptDt);
    plain.train.save_interval = 3;
    let mut frequent = plain.clone();
    frequent.train.resume_interval = 1;
    let (full, cut) = (tmp.path().join("full"), tmp.path().join("cut"));
    assert!(run(Some(plain), &full, false, None).finished);
    // Stopped after iteration 5: a resume point at 5, the last checkpoint at 3.
    run(Some(frequent), &cut, false, Some(5));
    let latest: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(cut.join("checkpoints/latest.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(latest["iteration"], 5, "{latest}");
    assert_eq!(latest["keep"], false, "{latest}");
    let names = |d: &Path| {
        let mut v: Vec<String> = std::fs::read_dir(d.join("checkpoints"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("step_"))
            .collect();
        v.sort();
        v
    };
    // the resume points at 1, 2 and 4 are gone; 3 (a checkpoint) and 5 (in force) remain
    assert_eq!(names(&cut), ["step_10.safetensors", "step_6.safetensors"]);
    assert!(run(None, &cut, true, None).finished);
    assert_eq!(lines(&full.join("metrics.jsonl")), lines(&cut.join("metrics.jsonl")));
    assert_eq!(lines(&full.join("eval.jsonl")), lines(&cut.join("eval.jsonl")));
    assert_eq!(names(&full), names(&cut));
    let w = |d: &Path| std::fs::read(d.join("checkpoints/step_12.safetensors")).unwrap();
    assert!(w(&full) == w(&cut), "final weights differ");
}

#[test]
fn interrupted_run_writes_nothing_more_and_resumes_to_the_same_run() {
    let _torch = pdt_testkit::process::libtorch(); // trains: seeds and draws from the process's generator
    let (tmp, data) = tiny_data();
    let mut cfg = runs::tiny_config(&data, Method::PromptDt);
    cfg.train.resume_interval = 1;
    let (full, cut) = (tmp.path().join("full"), tmp.path().join("cut"));
    assert!(run(Some(cfg.clone()), &full, false, None).finished);
    // A front end's Ctrl-C after iteration 3's report.
    let interrupt = pdt_base::stop::StopFlag::default();
    let mut progress = |p: &pdt_train::run::Progress| {
        if p.iteration == 3 {
            interrupt.set();
        }
    };
    let opts = TrainOptions {
        resume: false,
        resume_with: Default::default(),
        stop_after_iterations: None,
        progress: &mut progress,
        interrupt: interrupt.clone(),
        envs: None,
    };
    let err = train(Some(cfg), &cut, opts).unwrap_err();
    assert!(matches!(err, pdt_train::run::RunError::Interrupted { iteration: 4, .. }), "{err}");
    assert!(err.to_string().contains("interrupted during iteration 4"), "{err}");
    assert_eq!(lines(&cut.join("metrics.jsonl")).len(), 3);
    assert!(run(None, &cut, true, None).finished);
    assert_eq!(lines(&full.join("metrics.jsonl")), lines(&cut.join("metrics.jsonl")));
    assert_eq!(lines(&full.join("eval.jsonl")), lines(&cut.join("eval.jsonl")));
    let w = |d: &Path| std::fs::read(d.join("checkpoints/step_12.safetensors")).unwrap();
    assert!(w(&full) == w(&cut), "final weights differ");
}
