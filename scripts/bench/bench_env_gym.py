#!/usr/bin/env python3
"""Python side of the environment-throughput benchmark (the Rust side is `pdt_envs::bench`).

    .venv/bin/pip install "gymnasium[mujoco]==1.4.0"   # once; the extra adds imageio, which
                                                      # gymnasium.envs.mujoco imports
    .venv/bin/python scripts/bench/bench_env_gym.py [--steps 20000] [--seed 0]
        [--max-episode-steps 200] [--families cheetah,ant] [--no-mujoco]

Two engines, one environment each, stepped in a plain loop on one thread:

gymnasium  `gym.make("HalfCheetah-v5")` / `gym.make("Ant-v5")` with the default environment
           arguments and wrappers (PassiveEnvChecker, OrderEnforcing, TimeLimit). Ant-v5's defaults
           include the contact forces `cfrc_ext` in the observation (105 values) and the healthy
           check (terminates when torso z leaves [0.2, 1.0]); both are kept. Every gymnasium MuJoCo
           env calls `mj_rnePostConstraint` after `mj_step(nstep=5)`. The time limit is set to
           `--max-episode-steps` (default 200, the Prompt-DT horizon the Rust environments truncate
           at, so both reset equally often; 0 keeps gymnasium's default of 1000).
           Loop: `obs, r, term, trunc, info = env.step(a)`; `env.reset()` when term or trunc.
mujoco     The official bindings on the same XML the Rust environments load
           (`crates/envs/assets/half_cheetah.xml`, `ant_dir.xml`): `data.ctrl[:] = a`,
           `mujoco.mj_step(model, data, nstep=5)`, and every `--max-episode-steps` steps
           `mj_resetData` + `mj_forward`. Physics only: no observation, reward or termination,
           so an upper bound for any Python environment on these bindings.

Actions: uniform in [-1, 1] (float32), drawn before the clock starts from numpy's
`default_rng(seed)`; resets happen inside the timed region. Prints one JSON line on stdout.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time

import mujoco
import numpy as np

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
ASSETS = os.path.join(ROOT, "crates", "envs", "assets")

FAMILIES = {
    # family: (gymnasium id, XML of the Rust environment, action dimension)
    "cheetah": ("HalfCheetah-v5", "half_cheetah.xml", 6),
    "ant": ("Ant-v5", "ant_dir.xml", 8),
}


def load_avg_1m():
    try:
        with open("/proc/loadavg") as f:
            return float(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def row(family, steps, resets, seconds):
    return {
        "family": family,
        "steps": steps,
        "resets": resets,
        "seconds": seconds,
        "steps_per_s": steps / seconds,
    }


def bench_gymnasium(family, actions, seed, max_episode_steps):
    import gymnasium as gym

    env_id = FAMILIES[family][0]
    kwargs = {"max_episode_steps": max_episode_steps} if max_episode_steps > 0 else {}
    env = gym.make(env_id, **kwargs)
    env.reset(seed=seed)
    step, reset = env.step, env.reset
    resets = 0
    t0 = time.perf_counter()
    for a in actions:
        _obs, _r, terminated, truncated, _info = step(a)
        if terminated or truncated:
            reset()
            resets += 1
    seconds = time.perf_counter() - t0
    info = {
        "id": env_id,
        "obs_dim": int(env.observation_space.shape[0]),
        "max_episode_steps": env.spec.max_episode_steps,
        "wrappers": str(env),
    }
    env.close()
    return row(family, len(actions), resets, seconds), info


def bench_mujoco(family, actions, max_episode_steps):
    model = mujoco.MjModel.from_xml_path(os.path.join(ASSETS, FAMILIES[family][1]))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    horizon = max_episode_steps if max_episode_steps > 0 else 1000
    mj_step, mj_reset, mj_forward = mujoco.mj_step, mujoco.mj_resetData, mujoco.mj_forward
    ctrl = data.ctrl
    resets = 0
    t = 0
    t0 = time.perf_counter()
    for a in actions:
        ctrl[:] = a
        mj_step(model, data, nstep=5)
        t += 1
        if t == horizon:
            mj_reset(model, data)
            mj_forward(model, data)
            resets += 1
            t = 0
    seconds = time.perf_counter() - t0
    return row(family, len(actions), resets, seconds)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    p.add_argument("--steps", type=int, default=20_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-episode-steps", type=int, default=200)
    p.add_argument("--families", default="cheetah,ant")
    p.add_argument("--no-mujoco", action="store_true", help="skip the plain mujoco loop")
    args = p.parse_args()

    import gymnasium as gym

    load_before = load_avg_1m()
    results, mujoco_results, envs = [], [], {}
    for family in [f.strip() for f in args.families.split(",") if f.strip()]:
        if family not in FAMILIES:
            p.error(f"unknown family {family!r} (known: {', '.join(FAMILIES)})")
        act_dim = FAMILIES[family][2]
        rng = np.random.default_rng(args.seed)
        actions = rng.uniform(-1.0, 1.0, size=(args.steps, act_dim)).astype(np.float32)
        r, info = bench_gymnasium(family, actions, args.seed, args.max_episode_steps)
        results.append(r)
        envs[family] = info
        if not args.no_mujoco:
            mujoco_results.append(bench_mujoco(family, actions, args.max_episode_steps))

    print(
        json.dumps(
            {
                "engine": "gymnasium",
                "gymnasium_version": gym.__version__,
                "mujoco_version": mujoco.__version__,
                "numpy_version": np.__version__,
                "python": platform.python_version(),
                "steps": args.steps,
                "seed": args.seed,
                "max_episode_steps": args.max_episode_steps or None,
                "envs": envs,
                "results": results,
                "mujoco_python": mujoco_results,
                "cores": os.cpu_count(),
                "load_avg_1m": load_before,
                "load_avg_1m_after": load_avg_1m(),
            }
        )
    )


if __name__ == "__main__":
    main()
