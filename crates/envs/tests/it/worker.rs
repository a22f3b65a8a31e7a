//! The Python environment worker (`pdt_envs::worker`) with a real gymnasium environment and with
//! small misbehaving ones written into a temporary directory: Pendulum-v1 through the worker gives
//! the same numbers, bit for bit, as gymnasium stepped alone; each failure (a factory that raises,
//! wrong spaces, a non-finite observation, an episode that never ends, a worker that dies or hangs)
//! is an error naming the task and the step; the worker goes with its `VecEnv`.
//!
//! Needs a Python that imports promptdt and gymnasium (`pdt_testkit::python`); skipped otherwise.

use std::path::{Path, PathBuf};
use std::process::Command;

use pdt_envs::vec_env::{EnvDims, VecEnv};
use pdt_envs::worker::{make_batch, WorkerSpec, WorkerTask};
use pdt_envs::EnvError;
use serde_json::json;

/// Misbehaving environments, imported by the worker from the test's directory.
const MODULE: &str = r#"
import os, sys, time
import numpy as np
import gymnasium as gym

class Toy(gym.Env):
    """obs = [step, pid, g]; reward = g * action; never ends by itself; misbehaves on request."""
    def __init__(self, g=1.0, obs_size=3, nan_at=None, exit_at=None, hang_at=None, raise_at=None):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_size,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.g, self.nan_at, self.exit_at, self.hang_at, self.raise_at = g, nan_at, exit_at, hang_at, raise_at
        self.t = 0
    def _obs(self):
        v = float("nan") if self.t == self.nan_at else float(self.t)
        return np.array([v, os.getpid(), self.g], dtype=np.float32)
    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}
    def step(self, action):
        self.t += 1
        print("a print from the environment", self.t)
        if self.t == self.exit_at:
            sys.stderr.buffer.write(b"bytes that are not UTF-8: \xff\xfe\n")
            print("the environment gives up", file=sys.stderr, flush=True)
            os._exit(3)
        if self.t == self.hang_at:
            time.sleep(60)
        if self.t == self.raise_at:
            raise RuntimeError("the physics broke")
        return self._obs(), float(self.g * action[0]), False, False, {"success": self.t >= 2}

def raising(g=1.0, **kw):
    if g < 0:
        raise ValueError(f"g must be positive, got {g}")
    return Toy(g=g, **kw)
"#;

fn dims(obs_dim: usize, horizon: usize) -> EnvDims {
    EnvDims { obs_dim, act_dim: 1, horizon }
}

fn spec(entry: &str, python: &Path, kwargs: serde_json::Value) -> WorkerSpec {
    WorkerSpec {
        entry: entry.into(),
        task_keyword: None,
        kwargs: kwargs.as_object().cloned().unwrap_or_default(),
        imports: Vec::new(),
        python: Some(python.to_path_buf()),
        step_timeout_s: 20.0,
    }
}

fn task(index: usize, g: f64) -> WorkerTask {
    WorkerTask { index, name: format!("g{g}"), params: json!({ "g": g }) }
}

/// The toy module in a fresh directory.
fn toy_dir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("toyenvs.py"), MODULE).expect("module written");
    dir
}

fn toy(
    python: &Path,
    kwargs: serde_json::Value,
    tasks: Vec<WorkerTask>,
    horizon: usize,
) -> (tempfile::TempDir, Result<VecEnv, EnvError>) {
    let dir = toy_dir();
    let venv =
        make_batch(&spec("toyenvs:raising", python, kwargs), dir.path(), tasks, dims(3, horizon));
    (dir, venv)
}

fn python() -> Option<PathBuf> {
    pdt_testkit::python::worker_python()
}

#[test]
fn pendulum_through_the_worker_is_gymnasium_bit_for_bit() {
    let Some(py) = python() else { return };
    let tasks = vec![task(0, 9.81), task(1, 4.0), task(1, 4.0)];
    let seeds = [7u64, 8, 9];
    let steps = 25;
    // Actions exact in binary, so both sides step with the same f32s.
    let action = |t: usize, i: usize| ((t * 3 + i) % 9) as f32 * 0.5 - 2.0;
    let dir = tempfile::tempdir().expect("tempdir");
    let mut venv =
        make_batch(&spec("Pendulum-v1", &py, json!({})), dir.path(), tasks, dims(3, 200))
            .unwrap_or_else(|e| panic!("{e}"));
    let mut got: Vec<Vec<u32>> = vec![Vec::new(); 3];
    let first = venv.reset(&seeds).unwrap_or_else(|e| panic!("{e}"));
    for (i, o) in first.iter().enumerate() {
        got[i].extend(o.iter().map(|v| v.to_bits()));
    }
    for t in 0..steps {
        let flat: Vec<f32> = (0..3).map(|i| action(t, i)).collect();
        for (i, s) in venv.step_flat(&flat, None).expect("step").into_iter().enumerate() {
            let s = s.expect("stepped").unwrap_or_else(|e| panic!("{e}"));
            assert!(!s.terminated && !s.truncated && s.success.is_none());
            got[i].extend(s.obs.iter().map(|v| v.to_bits()));
            got[i].push(s.reward.to_bits());
        }
    }
    // The same episodes in gymnasium alone, the numbers as float32 bits.
    let script = format!(
        "import gymnasium as gym, numpy as np, json\n\
         out = []\n\
         for i, (g, seed) in enumerate([(9.81, 7), (4.0, 8), (4.0, 9)]):\n\
         \x20   env = gym.make('Pendulum-v1', g=g)\n\
         \x20   o, _ = env.reset(seed=seed)\n\
         \x20   bits = list(np.asarray(o, np.float32).view(np.uint32))\n\
         \x20   for t in range({steps}):\n\
         \x20       a = np.float32((t * 3 + i) % 9 * 0.5 - 2.0)\n\
         \x20       o, r, *_ = env.step(np.array([a], np.float32))\n\
         \x20       bits += list(np.asarray(o, np.float32).view(np.uint32)) + [np.float32(r).view(np.uint32)]\n\
         \x20   out.append([int(b) for b in bits])\n\
         print(json.dumps(out))\n"
    );
    let out = Command::new(&py).args(["-c", &script]).output().expect("python runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let want: Vec<Vec<u32>> = serde_json::from_slice(&out.stdout).expect("bits");
    for i in 0..3 {
        assert_eq!(got[i].len(), want[i].len());
        assert_eq!(got[i], want[i], "episode {i} differs from gymnasium alone");
    }
    assert_ne!(got[0], got[1], "g must reach the environment");
}

#[test]
fn the_horizon_cuts_an_episode_that_never_ends_and_success_is_read() {
    let Some(py) = python() else { return };
    let (_dir, venv) = toy(&py, json!({}), vec![task(0, 2.0)], 4);
    let mut venv = venv.unwrap_or_else(|e| panic!("{e}"));
    venv.reset(&[1]).expect("reset");
    let mut flags = Vec::new();
    for _ in 0..4 {
        let s = venv.step_flat(&[0.5], None).expect("step").remove(0).expect("slot").expect("ok");
        assert_eq!(s.reward, 1.0);
        flags.push((s.truncated, s.success));
    }
    assert_eq!(
        flags,
        vec![(false, Some(false)), (false, Some(true)), (false, Some(true)), (true, Some(true))]
    );
    // Stepping past the end is refused, as for the built-in environments, without a request.
    let after = venv.step_flat(&[0.5], None).expect("call").remove(0).expect("slot");
    assert!(matches!(after, Err(EnvError::Finished { .. })), "{after:?}");
}

fn message(r: Result<VecEnv, EnvError>) -> String {
    match r {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn a_factory_that_raises_or_gives_wrong_spaces_is_named() {
    let Some(py) = python() else { return };
    let (_d, r) = toy(&py, json!({}), vec![task(0, 1.0), task(1, -2.0)], 10);
    let m = message(r);
    assert!(m.contains("g-2 (task 1)"), "{m}");
    assert!(m.contains("ValueError: g must be positive, got -2.0"), "{m}");
    let (_d, r) = toy(&py, json!({ "obs_size": 4 }), vec![task(3, 1.0)], 10);
    let m = message(r);
    assert!(m.contains("g1 (task 3)") && m.contains("observation space has shape (4,)"), "{m}");
    assert!(m.contains("suite declares 3"), "{m}");
    let dir = toy_dir();
    let r = make_batch(
        &spec("toyenvs:nothing", &py, json!({})),
        dir.path(),
        vec![task(0, 1.0)],
        dims(3, 5),
    );
    let m = message(r);
    assert!(m.contains("toyenvs:nothing") && m.contains("AttributeError"), "{m}");
    let missing = Path::new("/nonexistent/python");
    let r = make_batch(
        &spec("Pendulum-v1", missing, json!({})),
        dir.path(),
        vec![task(0, 1.0)],
        dims(3, 5),
    );
    let m = message(r);
    assert!(m.contains("cannot start the worker's Python `/nonexistent/python`"), "{m}");
}

#[test]
fn a_non_finite_observation_or_a_raising_step_names_task_and_step() {
    let Some(py) = python() else { return };
    // Each task's misbehaviour comes with its parameters.
    let raising = WorkerTask { params: json!({ "g": 1.0, "raise_at": 5 }), ..task(0, 1.0) };
    let nan = WorkerTask { params: json!({ "g": 1.5, "nan_at": 3 }), ..task(1, 1.5) };
    let (_d, venv) = toy(&py, json!({}), vec![raising, nan], 10);
    let mut venv = venv.unwrap_or_else(|e| panic!("{e}"));
    venv.reset(&[1, 2]).expect("reset");
    for _ in 0..2 {
        let out = venv.step_flat(&[0.1, 0.2], None).expect("step");
        assert!(out.iter().all(|s| matches!(s, Some(Ok(_)))));
    }
    let out = venv.step_flat(&[0.1, 0.2], None).expect("step");
    let m = out[1].as_ref().expect("slot").as_ref().expect_err("NaN refused").to_string();
    assert!(m.contains("g1.5 (task 1), step 3") && m.contains("non-finite observation"), "{m}");
    // Episode 1 ended with its error; episode 0 goes on until its step raises.
    let out = venv.step_flat(&[0.1, 0.2], Some(&[true, false])).expect("step");
    assert!(matches!(out[0], Some(Ok(_))) && out[1].is_none());
    let out = venv.step_flat(&[0.1, 0.2], Some(&[true, false])).expect("step");
    let m = out[0].as_ref().expect("slot").as_ref().expect_err("raised").to_string();
    assert!(
        m.contains("g1 (task 0), step 5") && m.contains("RuntimeError: the physics broke"),
        "{m}"
    );
}

#[test]
fn a_worker_that_dies_or_hangs_is_an_error_and_the_worker_goes_with_its_vec_env() {
    let Some(py) = python() else { return };
    let (_d, venv) = toy(&py, json!({ "exit_at": 2 }), vec![task(4, 1.0)], 10);
    let mut venv = venv.unwrap_or_else(|e| panic!("{e}"));
    venv.reset(&[1]).expect("reset");
    venv.step_flat(&[0.0], None).expect("first step");
    let m = venv.step_flat(&[0.0], None).expect_err("died").to_string();
    assert!(m.contains("g1 (task 4), step 2"), "{m}");
    assert!(m.contains("exit status: 3") && m.contains("the environment gives up"), "{m}");
    let m = venv.step_flat(&[0.0], None).expect_err("gone").to_string();
    assert!(m.contains("gone since an earlier failure"), "{m}");

    let mut s = spec("toyenvs:raising", &py, json!({ "hang_at": 1 }));
    s.step_timeout_s = 1.0;
    let dir = toy_dir();
    let mut venv = make_batch(&s, dir.path(), vec![task(0, 1.0)], dims(3, 10)).expect("made");
    let first = venv.reset(&[1]).expect("reset");
    let pid = first[0][1] as u32;
    let m = venv.step_flat(&[0.0], None).expect_err("hung").to_string();
    assert!(m.contains("step 1") && m.contains("did not answer within 1 s"), "{m}");
    assert!(!Path::new(&format!("/proc/{pid}")).exists(), "the hung worker {pid} was killed");

    let (_d, venv) = toy(&py, json!({}), vec![task(0, 1.0)], 10);
    let mut venv = venv.unwrap_or_else(|e| panic!("{e}"));
    let pid = venv.reset(&[1]).expect("reset")[0][1] as u32;
    assert!(Path::new(&format!("/proc/{pid}")).exists(), "worker {pid} running");
    drop(venv);
    assert!(!Path::new(&format!("/proc/{pid}")).exists(), "worker {pid} outlived its VecEnv");
}
