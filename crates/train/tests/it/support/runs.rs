//! Helpers for the tests that train small runs (`resume.rs`, `macaw_run.rs`, `flat_optim.rs`,
//! `packs.rs`): a tiny scripted dataset, a tiny run's configuration, a run driven to a given stop,
//! and its logs without wall-clock fields.
#![allow(dead_code, clippy::unwrap_used, clippy::result_large_err)] // each including test uses its part

use pdt_rundir::config::{Method, TrainConfig};
use pdt_train::run::{train, RunError, TrainOptions, TrainSummary};
use std::path::{Path, PathBuf};

/// A temp dir with a small point-robot dataset in `data/`.
pub fn tiny_data() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let collect = pdt_envs::collect_scripted::CollectConfig {
        episodes_per_task: 4,
        prompt_episodes: 2,
        ..pdt_envs::collect_scripted::CollectConfig::for_family(
            pdt_envs::collect_scripted::ScriptedFamily::named("point_robot").unwrap(),
        )
    };
    pdt_envs::collect_scripted::collect(&collect, &data, &mut |_, _| {}).unwrap();
    (tmp, data)
}

/// A tiny point-robot run on `data`: 6 iterations of 2 steps, evaluated and saved every 2, with
/// a train-task evaluation at 5 and MT-BC-Finetune's fine-tuning kept small.
pub fn tiny_config(data: &Path, method: Method) -> TrainConfig {
    let mut c: TrainConfig = toml::from_str(
        r#"
        [env]
        name = "point_robot"
        [sampler]
        k = 4
        batch_size_per_task = 1
        [model]
        hidden_size = 16
        n_layer = 1
        n_inner = 32
        [optim]
        learning_rate = 1e-3
        warmup_steps = 3
        [train]
        iterations = 6
        steps_per_iteration = 2
        test_eval_interval = 2
        train_eval_interval = 5
        save_interval = 2
        [eval]
        episodes = 2
        finetune_steps = 2
        finetune_batch = 4
        [run]
        threads = 1
        device = "cpu"
        "#,
    )
    .unwrap();
    c.data.dir = data.to_path_buf();
    c.run.method = method;
    c
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
            envs: None,
        },
    )
}
