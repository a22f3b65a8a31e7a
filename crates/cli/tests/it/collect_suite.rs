//! `promptdt collect --env suite.toml --policy module:callable` (issue 53 item 4): a task suite's
//! datasets collected in its environment (gymnasium's Pendulum-v1, gravity `g` the task) by the
//! worker, and the same collection from Python (`promptdt.collect(suite, policy=...)`), which
//! writes the same bytes; a policy that raises is an error naming the task and step, no card.
//!
//! Needs a Python that imports promptdt and gymnasium (`pdt_testkit::python`); skipped otherwise.
#![allow(clippy::unwrap_used)] // test helpers: a failed unwrap is a failed test

use crate::cli::{fails, ok, s};
use std::path::Path;
use std::process::Command;

const POLICY: &str = r#"
import numpy as np

def swing(obs, task):
    return np.array([np.clip(2.0 * np.sign(obs[2]) * 10.0 / task["params"]["g"], -2.0, 2.0)])

def raising(obs, task):
    if task["index"] == 1:
        raise RuntimeError("no torque today")
    return [0.0]
"#;

fn suite(dir: &Path, python: &Path) -> std::path::PathBuf {
    let text = format!(
        "name = \"pend_cli\"\nobs_dim = 3\nact_dim = 1\naction_bound = 2.0\nmax_ep_len = 15\n\
         rtg_scale = 100\ntarget_return = 0.0\nprompt_length = 5\n\
         [[tasks]]\nname = \"light\"\nparams = {{ g = 5.0 }}\n\
         [[tasks]]\nname = \"heavy\"\nparams = {{ g = 12.0 }}\n\
         [splits.default]\ntrain = [\"light\"]\ntest = [\"heavy\"]\n\
         [environment]\nentry = \"Pendulum-v1\"\npython = {python:?}\nstep_timeout_s = 30\n"
    );
    std::fs::write(dir.join("pend_policy.py"), POLICY).unwrap();
    let path = dir.join("suite.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// Every file of `dir` (name, bytes), sorted; `card`: with `dataset.json`.
fn files(dir: &Path, card: bool) -> Vec<(String, Vec<u8>)> {
    let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| card || p.extension().is_some_and(|x| x == "safetensors"))
        .map(|p| {
            (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap())
        })
        .collect();
    out.sort();
    out
}

#[test]
fn the_cli_and_python_collect_the_same_bytes_from_a_policy() {
    let Some(py) = pdt_testkit::python::worker_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let suite = suite(tmp.path(), &py);
    let cli = tmp.path().join("cli");
    let args = ["--episodes", "4", "--prompt-episodes", "2", "--seed", "3"];
    let mut collect = vec!["collect", "--env", s(&suite), "--policy", "pend_policy:swing"];
    collect.extend(args);
    collect.extend(["--envs-per-task", "3", "--out", s(&cli)]);
    let out = ok(&collect);
    assert!(out.contains("wrote 12 datasets"), "{out}");
    assert_eq!(files(&cli, true).len(), 13, "2 tasks x 3 levels x (dataset, prompts) + card");

    // From Python: the suite's [environment] in-process, and a factory of the same environment.
    let script = format!(
        "import sys, gymnasium as gym\n\
         sys.path.insert(0, {dir:?})\n\
         import promptdt, pend_policy\n\
         kw = dict(seed=3, episodes=4, prompt_episodes=2, progress=False)\n\
         promptdt.collect({suite:?}, {a:?}, policy=pend_policy.swing, envs_per_task=1, **kw)\n\
         make = lambda task: gym.make('Pendulum-v1', **task['params'])\n\
         promptdt.collect({suite:?}, {b:?}, policy=pend_policy.swing, factory=make, **kw)\n",
        dir = s(tmp.path()),
        suite = s(&suite),
        a = s(&tmp.path().join("py")),
        b = s(&tmp.path().join("factory")),
    );
    let run = Command::new(&py).args(["-c", &script]).output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    assert_eq!(files(&cli, true), files(&tmp.path().join("py"), true), "the same bytes, card too");
    assert_eq!(files(&cli, false), files(&tmp.path().join("factory"), false));

    // A policy that raises: the task and the step named, no card.
    let bad = tmp.path().join("bad");
    let e = fails(&[
        "collect",
        "--env",
        s(&suite),
        "--policy",
        "pend_policy:raising",
        "--episodes",
        "2",
        "--out",
        s(&bad),
    ]);
    assert!(
        e.contains("heavy (task 1), step 1") && e.contains("RuntimeError: no torque today"),
        "{e}"
    );
    assert!(!bad.join("dataset.json").exists());
    // Flags of the other collections are refused for a suite.
    let e = fails(&[
        "collect",
        "--env",
        s(&suite),
        "--policy",
        "pend_policy:swing",
        "--from-pretrained",
    ]);
    assert!(e.contains("--from-pretrained is for the families collected by an RL agent"), "{e}");
    let e = fails(&["collect", "--env", "point_robot", "--policy", "pend_policy:swing"]);
    assert!(e.contains("--policy is for task suites"), "{e}");
}
