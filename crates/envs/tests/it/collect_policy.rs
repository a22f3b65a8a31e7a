//! Collection in a task suite's environment from a Python policy (`pdt_envs::collect_policy`),
//! through the worker process: gymnasium's Pendulum-v1 with its gravity `g` as the task and a
//! policy module beside the suite file. The same seed gives the same bytes, whatever the number
//! of environments stepped together; the levels are what the docs say; and a policy that raises,
//! returns the wrong shape or NaN, an environment that never ends, and a worker killed
//! mid-collection are each an error naming the task and the step, with no card written.
//!
//! Needs a Python that imports promptdt and gymnasium (`pdt_testkit::python`); skipped otherwise.

use std::path::{Path, PathBuf};

use pdt_data::mode::Mode;
use pdt_envs::collect_policy::{collect, PolicyCollectConfig, PolicySide};
use pdt_envs::collect_scripted::CollectError;
use pdt_envs::suite::SuiteFamily;

/// The policies: a swing-up heuristic for Pendulum, and misbehaving ones.
const POLICIES: &str = r#"
import os
import numpy as np

def swing(obs, task):
    """Torque along the angular velocity, harder in low gravity (the task is seen)."""
    g = task["params"]["g"]
    return np.array([np.clip(2.0 * np.sign(obs[2]) * 10.0 / g, -2.0, 2.0)], np.float64)

def weak(obs, task):
    return [0.25 * float(np.sign(obs[2]))]

def wild(obs, task):
    return np.array([5.0], np.float32)

def _at(obs):
    # Pendulum's observation does not count steps; the toy environment's obs[0] does.
    return int(obs[0])

def raising(obs, task):
    if task["index"] == 1 and _at(obs) == 3:
        raise ValueError("the controller diverged")
    return [0.0]

def wrong_shape(obs, task):
    return np.zeros(2 if _at(obs) == 2 else 1)

def nan_at_4(obs, task):
    return [float("nan") if _at(obs) == 4 else 0.0]

def dies(obs, task):
    if _at(obs) == 3 and task["index"] == 0:
        os._exit(7)
    return [0.0]
"#;

/// An environment that counts its steps in obs[0] and never ends by itself.
const TOY: &str = r#"
import numpy as np
import gymnasium as gym

class Counter(gym.Env):
    def __init__(self, g=1.0):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
        self.action_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)
        self.g, self.t = g, 0
    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.array([0.0, self.np_random.uniform(), self.g], np.float32), {}
    def step(self, action):
        self.t += 1
        return np.array([self.t, 0.0, self.g], np.float32), float(action[0]), False, False, {}
"#;

fn suite_text(entry: &str, python: &Path, horizon: usize) -> String {
    let tasks: String = [4.0, 9.81, 15.0]
        .iter()
        .enumerate()
        .map(|(i, g)| format!("[[tasks]]\nname = \"g{i}\"\nparams = {{ g = {g:?} }}\n"))
        .collect();
    format!(
        "name = \"pend\"\nobs_dim = 3\nact_dim = 1\naction_bound = 2.0\nmax_ep_len = {horizon}\n\
         rtg_scale = 100\ntarget_return = 0.0\nprompt_length = 5\n{tasks}\
         [splits.default]\ntrain = [\"g0\", \"g1\"]\ntest = [\"g2\"]\n\
         [environment]\nentry = \"{entry}\"\npython = {python:?}\nstep_timeout_s = 30\n"
    )
}

/// A directory with the suite file (`entry`, `horizon`), the policies and the toy environment.
fn setup(python: &Path, entry: &str, horizon: usize) -> (tempfile::TempDir, SuiteFamily) {
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("pend_policies.py"), POLICIES).expect("policies");
    std::fs::write(dir.path().join("counter_env.py"), TOY).expect("toy");
    let path = dir.path().join("pend.toml");
    std::fs::write(&path, suite_text(entry, python, horizon)).expect("suite");
    let suite = SuiteFamily::load(&path).unwrap_or_else(|e| panic!("{e}"));
    (dir, suite)
}

fn config(suite: &SuiteFamily, policy: &str, episodes: usize, lanes: usize) -> PolicyCollectConfig {
    let mut cfg = PolicyCollectConfig::new(suite, policy);
    cfg.episodes_per_task = episodes;
    cfg.envs_per_task = lanes;
    cfg.prompt_rule = "best:2".parse().expect("rule");
    cfg
}

fn run(suite: &SuiteFamily, cfg: &PolicyCollectConfig, out: &Path) -> Result<usize, CollectError> {
    let mut last = (0, 0);
    let summary = collect(suite, cfg, PolicySide::Worker, out, &mut |d, t| last = (d, t))?;
    // Progress counts every episode.
    assert_eq!(last.0, last.1);
    Ok(summary.entries.len() * 2)
}

/// Every file of `dir`, name and bytes, sorted.
fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .expect("dir")
        .map(|e| {
            let p = e.expect("entry").path();
            (
                p.file_name().expect("a name").to_string_lossy().into_owned(),
                std::fs::read(&p).expect("read"),
            )
        })
        .collect();
    out.sort();
    out
}

fn python() -> Option<PathBuf> {
    pdt_testkit::python::worker_python()
}

#[test]
fn pendulum_collection_is_a_function_of_the_seed_and_has_the_documented_levels() {
    let Some(py) = python() else { return };
    let (dir, suite) = setup(&py, "Pendulum-v1", 30);
    let mut cfg = config(&suite, "pend_policies:swing", 4, 3);
    let (a, b, c) = (dir.path().join("a"), dir.path().join("b"), dir.path().join("c"));
    assert_eq!(run(&suite, &cfg, &a).unwrap_or_else(|e| panic!("{e}")), 18);
    // Again, with one environment per task: the same bytes (the card included).
    cfg.envs_per_task = 1;
    run(&suite, &cfg, &b).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(files(&a), files(&b));
    assert_eq!(files(&a).len(), 19, "a dataset and a prompt set per task and level, and the card");
    // Another seed: other data.
    cfg.seed = 1;
    run(&suite, &cfg, &c).unwrap_or_else(|e| panic!("{e}"));
    assert_ne!(files(&a), files(&c));

    let read = |task: usize, mode: &str| {
        pdt_data::native::read_task_dataset(&a.join(format!("pend-{task}-{mode}.safetensors")))
            .unwrap_or_else(|e| panic!("{e}"))
    };
    for task in 0..3 {
        let expert = read(task, "expert");
        assert_eq!(expert.trajectories.len(), 4);
        for t in &expert.trajectories {
            // Pendulum never ends by itself: the suite's horizon cuts it.
            assert_eq!(t.rewards.len(), 30);
            assert!(t.truncated[29] && !t.terminated.iter().any(|&x| x));
            // The expert's actions are the policy's exactly (no noise by default): +-min(2, 20/g).
            let want = (20.0 / [4.0f64, 9.81, 15.0][task]).min(2.0) as f32;
            assert!(t.actions.iter().all(|a| a.abs() == want), "{:?}", &t.actions[..5]);
        }
        // Medium: the expert with noise, inside the bounds; random: uniform in the bounds.
        for mode in ["medium", "random"] {
            let acts: Vec<f32> =
                read(task, mode).trajectories.iter().flat_map(|t| t.actions.clone()).collect();
            assert!(acts.iter().all(|a| (-2.0..=2.0).contains(a)));
            let distinct = acts.iter().filter(|a| a.abs() != 2.0).count();
            assert!(distinct > acts.len() / 4, "{mode}: {:?}", &acts[..8]);
        }
        // The prompt set: the dataset's 2 episodes of highest return, best first.
        let mut returns: Vec<f64> = expert.returns();
        returns.sort_by(|x, y| y.total_cmp(x));
        assert_eq!(read(task, "prompt-expert").returns(), returns[..2].to_vec());
    }
    let card = std::fs::read_to_string(a.join("dataset.json")).expect("card");
    assert!(card.contains("pend_policies:swing") && card.contains("\"best:2\""), "{card}");
}

#[test]
fn a_second_policy_makes_the_medium_level() {
    let Some(py) = python() else { return };
    let (dir, suite) = setup(&py, "Pendulum-v1", 10);
    let mut cfg = config(&suite, "pend_policies:wild", 2, 2);
    cfg.medium = Some("pend_policies:weak".into());
    cfg.modes = vec![Mode::Expert, Mode::Medium];
    cfg.tasks = vec![2];
    let out = dir.path().join("out");
    assert_eq!(run(&suite, &cfg, &out).unwrap_or_else(|e| panic!("{e}")), 4);
    let read = |mode: &str| {
        pdt_data::native::read_task_dataset(&out.join(format!("pend-2-{mode}.safetensors")))
            .unwrap_or_else(|e| panic!("{e}"))
    };
    // The wild expert's 5.0 is clipped into the bounds; the medium policy's 0.25 is recorded.
    assert!(read("expert").trajectories.iter().all(|t| t.actions.iter().all(|&a| a == 2.0)));
    assert!(read("medium").trajectories.iter().all(|t| t.actions.iter().all(|&a| a.abs() == 0.25)));
}

#[test]
fn misbehaving_policies_and_workers_are_named_and_leave_no_card() {
    let Some(py) = python() else { return };
    let (dir, suite) = setup(&py, "counter_env:Counter", 8);
    let cases = [
        ("pend_policies:raising", "g1 (task 1), step 4", "ValueError: the controller diverged"),
        (
            "pend_policies:wrong_shape",
            ", step 3",
            "action of shape (2,) (2 values), but the suite declares act_dim = 1",
        ),
        ("pend_policies:nan_at_4", ", step 5", "non-finite action (action[0] = NaN)"),
        ("pend_policies:dies", "", "exit status: 7"),
        ("pend_policies:missing", "", "the expert policy `pend_policies:missing`: AttributeError"),
    ];
    for (policy, at, what) in cases {
        let out = dir.path().join(policy.replace(':', "_"));
        let e = run(&suite, &config(&suite, policy, 3, 2), &out).expect_err(policy).to_string();
        assert!(e.contains(at) && e.contains(what), "{policy}: {e}");
        assert!(!out.join("dataset.json").exists(), "{policy}: no card");
    }
    // An environment that never ends is cut at the horizon; with a good policy, all is written.
    let out = dir.path().join("fine");
    run(&suite, &config(&suite, "pend_policies:weak", 3, 2), &out)
        .unwrap_or_else(|e| panic!("{e}"));
    let ds =
        pdt_data::native::read_task_dataset(&out.join("pend-0-random.safetensors")).expect("read");
    assert!(ds.trajectories.iter().all(|t| t.rewards.len() == 8 && t.truncated[7]));
}
