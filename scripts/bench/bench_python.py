#!/usr/bin/env python3
"""Benchmarks of the Python package, side by side in one run (`benchmarks/08-python.json`).

    bash scripts/install_python.sh && .venv-promptdt/bin/pip install "gymnasium[mujoco]==1.4.0" mujoco==3.17.0
    .venv-promptdt/bin/python scripts/bench/bench_python.py [--torch-python .venv/bin/python] [--out target/bench-python]

1. Environment steps per second, HalfCheetah (cheetah_vel task 0) and Ant (ant_dir task 0), random
   actions in [-1, 1] drawn before the clock starts, a 200-step time limit, resets inside the timed
   region, counting only the steps that stepped physics:
   - the Rust loop (`pdt_envs::bench`, no Python in the loop): one env; 16 envs on 1 and 2 threads;
   - promptdt from Python: `promptdt.envs.make_vec` (gymnasium VectorEnv API, NEXT_STEP autoreset),
     1 env, and 16 envs on 1 and 2 threads;
   - gymnasium 1.4.0's `HalfCheetah-v5` / `Ant-v5`: `gym.make` (one env, reset on term/trunc) and
     `gym.make_vec(..., vectorization_mode="sync")` with 16 envs.
2. `Policy.act` latency (ms per call) at batch 1 and 50, one libtorch thread, against the PyTorch
   reference model's `get_action` (scripts/bench/bench_act_torch.py, run by `--torch-python`): the
   same architecture (hidden 128, 3 layers, 1 head), point-robot dims, K = 20, a 5-step prompt;
   synthetic observations and rewards, 100 calls per episode (the K-window full after 20).
Writes results.json and prints Markdown tables.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

import promptdt
from promptdt import _native
from promptdt.envs import make_vec

ROOT = pathlib.Path(__file__).resolve().parents[2]
GYM_IDS = {"cheetah_vel": "HalfCheetah-v5", "ant_dir": "Ant-v5"}
ACT = {"cheetah_vel": 6, "ant_dir": 8}


def vec_loop(env_step, actions, n_envs, autoreset):
    """Steps with actions[t]; returns (physics steps, seconds)."""
    pending = np.zeros(n_envs, dtype=bool)
    steps = 0
    t0 = time.perf_counter()
    for a in actions:
        term, trunc = env_step(a)
        steps += n_envs - int(pending.sum()) if autoreset else n_envs
        pending = term | trunc
    return steps, time.perf_counter() - t0


def bench_envs(family, steps_single, steps_vec, seed):
    rows = []
    rust = json.loads(_native.bench_envs([family], steps_single, 16, [1, 2], seed))
    for r in rust:
        name = "Rust loop, 1 env" if r["mode"] == "single" else f"Rust loop, 16 envs, {r['threads']} threads"
        rows.append((name, r["steps_per_s"]))
    rng = np.random.default_rng(seed)
    for n, threads, steps in [(1, 1, steps_single), (16, 1, steps_vec), (16, 2, steps_vec)]:
        env = make_vec(family, n, task=0, threads=threads)
        env.reset(seed=seed)
        acts = rng.uniform(-1, 1, (steps, n, ACT[family])).astype(np.float32)

        def step(a, env=env):
            _, _, term, trunc, _ = env.step(a)
            return term, trunc

        s, sec = vec_loop(step, acts, n, autoreset=True)
        label = "promptdt make_vec from Python, 1 env" if n == 1 else f"promptdt make_vec from Python, 16 envs, {threads} threads"
        rows.append((label, s / sec))
    try:
        import gymnasium as gym
    except ImportError:
        return rows
    gid = GYM_IDS[family]
    env = gym.make(gid, max_episode_steps=200)
    env.reset(seed=seed)
    acts = rng.uniform(-1, 1, (steps_single, ACT[family])).astype(np.float32)
    t0 = time.perf_counter()
    for a in acts:
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
    rows.append((f"gymnasium {gym.__version__} {gid}, 1 env", steps_single / (time.perf_counter() - t0)))
    venv = gym.make_vec(gid, num_envs=16, vectorization_mode="sync", max_episode_steps=200)
    venv.reset(seed=seed)
    acts = rng.uniform(-1, 1, (steps_vec, 16, ACT[family])).astype(np.float32)

    def gstep(a):
        _, _, term, trunc, _ = venv.step(a)
        return term, trunc

    s, sec = vec_loop(gstep, acts, 16, autoreset=True)
    rows.append((f"gymnasium {gym.__version__} {gid}, make_vec sync, 16 envs", s / sec))
    return rows


def tiny_run(work):
    data = work / "data"
    promptdt.collect("point_robot", data, seed=0, episodes=5, prompt_episodes=2)
    text = (ROOT / "configs/point_robot/demo.toml").read_text()
    text = text.replace("k = 10", "k = 20").replace("iterations = 40", "iterations = 1")
    text = text.replace("[eval]\nepisodes = 20", "[eval]\nepisodes = 1")
    text = text.replace("[run]\n", "[run]\nthreads = 1\ndevice = \"cpu\"\n")
    cfg = work / "bench.toml"
    cfg.write_text(text)
    promptdt.train(work / "run", cfg, data=data)
    return work / "run"


def bench_act(run, batch, steps, repeats):
    policy = promptdt.Policy.load(run, threads=1)
    assert policy.k == 20 and policy.prompt_steps == 5, (policy.k, policy.prompt_steps)
    policy.set_prompt(policy.task_prompt(2))
    rng = np.random.default_rng(0)

    def episode():
        policy.reset(batch)
        obs = rng.standard_normal((batch, 2)).astype(np.float32)
        t0 = time.perf_counter()
        act = policy.act(obs)
        for _ in range(steps - 1):
            obs = rng.standard_normal((batch, 2)).astype(np.float32)
            rew = rng.standard_normal(batch).astype(np.float32)
            act = policy.act(obs, rew)
        assert act.shape == (batch, 2)
        return (time.perf_counter() - t0) / steps

    episode()
    return statistics.median(episode() for _ in range(repeats))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--torch-python", default=str(ROOT / ".venv/bin/python"))
    ap.add_argument("--out", default=str(ROOT / "target/bench-python"))
    ap.add_argument("--steps", type=int, default=20000, help="steps of the 1-env runs")
    ap.add_argument("--vec-steps", type=int, default=2000, help="steps of each env in the 16-env runs")
    ap.add_argument("--act-steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()[0]
    result = {"promptdt": promptdt.__version__, "cpu_count": os.cpu_count(), "envs": {}, "act": []}
    for family in ("cheetah_vel", "ant_dir"):
        result["envs"][family] = bench_envs(family, args.steps, args.vec_steps, args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        run = tiny_run(pathlib.Path(tmp))
        promptdt.set_num_threads(1)
        for batch in (1, 50):
            ours = bench_act(run, batch, args.act_steps, args.repeats)
            torch_ms = None
            if args.torch_python and pathlib.Path(args.torch_python).exists():
                cmd = [args.torch_python, str(ROOT / "scripts/bench/bench_act_torch.py"), "--batch", str(batch),
                       "--threads", "1", "--steps", str(args.act_steps), "--repeats", str(args.repeats)]
                torch_ms = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)["ms_per_call"]
            result["act"].append({"batch": batch, "promptdt_ms": round(1e3 * ours, 4), "pytorch_ms": torch_ms})
    result["load_avg_1m"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    (out / "results.json").write_text(json.dumps(result, indent=1))
    for family, rows in result["envs"].items():
        print(f"\n| {family} | steps/s |\n|---|---:|")
        for name, sps in rows:
            print(f"| {name} | {sps:,.0f} |")
    print("\n| Policy.act, 1 thread | promptdt ms/call | PyTorch get_action ms/call | speed-up |\n|---|---:|---:|---:|")
    for r in result["act"]:
        sp = f"{r['pytorch_ms'] / r['promptdt_ms']:.2f}x" if r["pytorch_ms"] else "-"
        print(f"| batch {r['batch']} | {r['promptdt_ms']:.3f} | {r['pytorch_ms'] or '-'} | {sp} |")
    print(f"\nload average 1 min before/after: {result['load_avg_1m']}; results in {out / 'results.json'}")


if __name__ == "__main__":
    main()
