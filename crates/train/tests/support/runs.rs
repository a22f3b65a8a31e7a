//! Helpers for the tests that train small runs (`resume.rs`, `macaw_run.rs`): a tiny scripted
//! dataset, a run driven to a given stop, and its logs without wall-clock fields.
#![allow(dead_code, clippy::unwrap_used, clippy::result_large_err)] // each including test uses its part

use pdt_train::config::TrainConfig;
use pdt_train::run::{train, RunError, TrainOptions, TrainSummary};
use std::path::{Path, PathBuf};

/// A temp dir with a small point-robot dataset in `data/`.
pub fn tiny_data() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let collect = pdt_envs::collect_scripted::CollectConfig {
        episodes_per_task: 4,
        prompt_episodes: 2,
        ..Default::default()
    };
    pdt_envs::collect_scripted::collect(&collect, &data, &mut |_, _| {}).unwrap();
    (tmp, data)
}

/// The lines of a JSONL log with wall-clock fields removed.
pub fn lines(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| {
            let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
            v.as_object_mut().unwrap().remove("time/elapsed_s");
            v
        })
        .collect()
}

/// Trains `cfg` (or resumes the run in `dir` when `cfg` is `None` and `resume`), stopping after
/// `stop` iterations when given.
pub fn run(
    cfg: Option<TrainConfig>,
    dir: &Path,
    resume: bool,
    stop: Option<u64>,
) -> Result<TrainSummary, RunError> {
    let mut progress = |_: &pdt_train::run::Progress| {};
    train(
        cfg,
        dir,
        TrainOptions {
            resume,
            resume_with: Default::default(),
            stop_after_iterations: stop,
            progress: &mut progress,
            interrupt: Default::default(),
        },
    )
}
