//! Helpers shared by the CLI tests: the real binary, a tiny point-robot dataset and experiment.
#![allow(dead_code)] // each test file uses a part
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub fn promptdt<S: AsRef<str> + std::fmt::Debug>(args: &[S]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_promptdt"))
        .args(args.iter().map(AsRef::<str>::as_ref))
        .output()
        .expect("binary runs")
}

/// Runs the binary in `cwd`.
pub fn promptdt_in<S: AsRef<str> + std::fmt::Debug>(cwd: &Path, args: &[S]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_promptdt"))
        .current_dir(cwd)
        .args(args.iter().map(AsRef::<str>::as_ref))
        .output()
        .expect("binary runs")
}

pub fn check_ok<S: AsRef<str> + std::fmt::Debug>(args: &[S], out: Output) -> String {
    let (stdout, stderr) =
        (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "promptdt {args:?} failed:\n{stdout}\n{stderr}");
    stdout.into_owned()
}

pub fn check_fails<S: AsRef<str> + std::fmt::Debug>(args: &[S], out: Output) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "promptdt {args:?} should fail");
    // A clear error, never a panic or an abort.
    assert!(
        !stderr.contains("panicked") && out.status.code().is_some(),
        "promptdt {args:?} crashed:\n{stderr}"
    );
    stderr
}

pub fn ok<S: AsRef<str> + std::fmt::Debug>(args: &[S]) -> String {
    check_ok(args, promptdt(args))
}

pub fn fails<S: AsRef<str> + std::fmt::Debug>(args: &[S]) -> String {
    check_fails(args, promptdt(args))
}

/// `rel` inside the checkout.
#[allow(unused_imports)] // each test file uses a part
pub use pdt_testkit::fs::repo;

pub const TINY: &str = r#"
[env]
name = "point_robot"
[sampler]
k = 4
batch_size_per_task = 1
[model]
hidden_size = 16
n_layer = 1
n_inner = 32
[train]
iterations = 8
steps_per_iteration = 2
test_eval_interval = 4
train_eval_interval = 0
save_interval = 2
[eval]
episodes = 2
[run]
threads = 1
device = "cpu"
"#;

/// Collects a tiny point-robot dataset into `data`.
pub fn tiny_data(data: &Path) {
    let msg = ok(&[
        "collect",
        "--env",
        "point-robot",
        "--out",
        data.to_str().unwrap(),
        "--episodes",
        "3",
        "--prompt-episodes",
        "2",
    ]);
    assert!(msg.contains("wrote 240 datasets"), "{msg}");
}

/// A tiny dataset and experiment file in `dir`.
pub fn tiny_setup(dir: &Path) -> PathBuf {
    let data = dir.join("data");
    tiny_data(&data);
    assert!(
        data.join("point_robot-7-prompt-expert.safetensors").is_file()
            && data.join("dataset.json").is_file()
    );
    let cfg = dir.join("tiny.toml");
    std::fs::write(&cfg, format!("{TINY}\n[data]\ndir = {:?}\n", data.to_str().unwrap())).unwrap();
    cfg
}

/// Rewrites every file of task 0 in `data` (from [`tiny_data`]) through `f`.
pub fn edit_task0(data: &Path, f: impl Fn(&mut pdt_data::Trajectory)) {
    for mode in ["expert", "prompt-expert"] {
        let path = data.join(format!("point_robot-0-{mode}.safetensors"));
        let meta = pdt_data::native::read_file_meta(&path).unwrap();
        let mut ds = pdt_data::native::read_task_dataset(&path).unwrap();
        for t in &mut ds.trajectories {
            f(t);
        }
        pdt_data::native::write_task_dataset(&path, &ds, &meta).unwrap();
    }
}

/// Every `train/action_loss` of a run's metrics (one per iteration).
pub fn action_losses(run: &Path) -> Vec<f64> {
    std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|v| v["train/action_loss"].as_f64().unwrap())
        .collect()
}

/// The training losses of a run (its metrics lines without the wall-clock field).
pub fn losses(run: &Path) -> Vec<String> {
    std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| l.split("\"time/elapsed_s\"").next().unwrap().to_string())
        .collect()
}

/// A tiny experiment manifest: two point-robot cells (Prompt-DT, MT-ORL) at a `smoke` budget of
/// seconds, `seeds` seeds each, with one claim.
pub fn tiny_manifest(name: &str, title: &str, purpose: &str, seeds: u32) -> String {
    format!(
        r#"name = "{name}"
title = "{title}: a tiny point-robot experiment"
description = "Two point-robot cells, for the tests of {purpose}."
layout = "curves"

[[claims]]
text = "Prompt-DT beats MT-ORL"
kind = "better"
a = "point_robot/prompt-dt"
b = "point_robot/mt-orl"

[budgets.smoke]
note = "seconds"
iterations = 2
steps_per_iteration = 2
batch_size_per_task = 1
eval_episodes = 1
test_eval_interval = 1
train_eval_interval = 0
save_interval = 1
seeds = {seeds}
data_episodes = 2
prompt_set_episodes = 2

[[cells]]
env = "point_robot"
method = "prompt-dt"
paper = 1.0

[[cells]]
env = "point_robot"
method = "mt-orl"
paper = 1.0
"#
    )
}

/// A path as the `&str` an argument list takes.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `promptdt train --config CFG --out OUT --quiet EXTRA...`, which must succeed.
pub fn train(cfg: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args = vec!["train", "--config", s(cfg), "--out", s(out), "--quiet"];
    args.extend_from_slice(extra);
    ok(&args)
}

/// The tiny experiment with `key = value` set in `section` (TOML value syntax).
pub fn variant(cfg: &Path, section: &str, key: &str, value: &str) -> PathBuf {
    let mut doc: toml::Table = std::fs::read_to_string(cfg).unwrap().parse().unwrap();
    let v: toml::Table = format!("v = {value}").parse().unwrap();
    let table = doc.entry(section).or_insert(toml::Value::Table(toml::Table::new()));
    table.as_table_mut().unwrap().insert(key.into(), v["v"].clone());
    let path = cfg.with_file_name(format!("{section}-{key}.toml"));
    std::fs::write(&path, toml::to_string(&doc).unwrap()).unwrap();
    path
}
