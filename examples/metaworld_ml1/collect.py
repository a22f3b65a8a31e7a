"""Collects an ML1 suite's datasets with Meta-World's own scripted policies, for promptdt.

    python collect.py push-v3.toml data/push-v3 [--jobs 2]

For each of the suite's tasks (a goal of ``ML1(env_name, seed)``, ``mw_envs.make``), into OUT:

- ``{name}-{i}-expert.safetensors``: ``--expert-episodes`` episodes of the scripted policy
  (``metaworld.policies.Sawyer...V3Policy``) with Gaussian action noise of std ``--expert-noise``
  (0.1, the noise Meta-World's own tests check its scripted policies' success at; without noise every
  episode of a task would be the same one: the task fixes the start and the policy is deterministic);
- ``{name}-{i}-medium.safetensors``: the same policy with noise std ``--medium-noise`` (0.6: about a
  third to two thirds of the episodes still succeed);
- ``{name}-{i}-random.safetensors``: uniform random actions (the random returns of the normalised score);
- ``{name}-{i}-prompt-{expert,medium}.safetensors``: the prompt sets, by the best-return rule (the
  ``--prompt-episodes`` episodes of highest return of the task's data, best first: as the reference
  release's prompt files and ``promptdt data import --prompt-rule best:N``);
- ``dataset.json``: the dataset card (per task and file: episodes, steps, return statistics), which
  ``promptdt reproduce`` reads for the normalised scores (expert and random mean returns per task).

Every file is written with ``promptdt.write_dataset`` (checked against the suite, atomic), and a
file that exists is not collected again: a killed collection continues where it stopped. Each
episode's noise comes from its own generator, seeded by (``--seed``, task, mode, episode), so the
data do not depend on the order or the number of jobs.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import tomllib
import warnings
from multiprocessing import Pool
from pathlib import Path
from typing import Any, Dict, Tuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import mw_envs  # noqa: E402

MODES = {"expert": 0, "medium": 1, "random": 2}


def episode(env: Any, policy: Any, noise: float | None, rng: np.random.Generator):
    """One episode of ``mw_envs.HORIZON`` steps: ``noise`` None plays uniform random actions."""
    import promptdt

    obs, _ = env.reset(seed=0)  # Meta-World ignores the seed (mw_envs)
    o, a, r = [], [], []
    for _ in range(mw_envs.HORIZON):
        if noise is None:
            act = rng.uniform(-1.0, 1.0, 4)
        else:
            act = policy.get_action(mw_envs.policy_observation(env, obs))
            act = act + noise * rng.standard_normal(4)
        act = np.clip(act, -1.0, 1.0).astype(np.float32)
        o.append(np.asarray(obs, np.float32))
        a.append(act)
        obs, rew, term, trunc, _info = env.step(act)
        r.append(rew)
        if term or trunc:
            break
    n = len(r)
    ends = np.zeros(n, bool)
    ends[-1] = True
    # Meta-World never terminates; its time limit (max_path_length) truncates the episode.
    return promptdt.Trajectory(observations=np.stack(o), actions=np.stack(a),
                               rewards=np.asarray(r, np.float32), terminated=np.zeros(n, bool),
                               truncated=ends)


def collect_task(job: Tuple[Dict[str, Any], int]) -> str:
    args, i = job
    warnings.filterwarnings("ignore", module="metaworld")  # the policies' "Constant(s) may be too high"
    import promptdt

    suite = tomllib.loads(Path(args["suite"]).read_text())
    env_kw = suite["environment"]["kwargs"]
    params = suite["tasks"][i]["params"]
    name, out = suite["name"], Path(args["out"])
    policy = mw_envs.scripted_policy(env_kw["env_name"])
    done = []
    for mode, noise, count in (("expert", args["expert_noise"], args["expert_episodes"]),
                               ("medium", args["medium_noise"], args["medium_episodes"]),
                               ("random", None, args["random_episodes"])):
        path = out / f"{name}-{i}-{mode}.safetensors"
        prompt = out / f"{name}-{i}-prompt-{mode}.safetensors"
        if not path.exists():
            trajs = []
            for e in range(count):
                env = mw_envs.make(env_kw["env_name"], env_kw["ml1_seed"], params)
                rng = np.random.default_rng([args["seed"], i, MODES[mode], e])
                trajs.append(episode(env, policy, noise, rng))
                env.close()
            ds = promptdt.Dataset(obs_dim=39, act_dim=4, trajectories=trajs, env=args["suite"],
                                  task=i, mode=mode)
            promptdt.write_dataset(path, ds)
            done.append(mode)
        if mode != "random" and not prompt.exists():
            ds = promptdt.load_dataset(path)
            best = sorted(ds.trajectories, key=lambda t: -t.episode_return)[: args["prompt_episodes"]]
            promptdt.write_dataset(prompt, promptdt.Dataset(
                obs_dim=39, act_dim=4, trajectories=best, env=args["suite"], task=i,
                mode=f"prompt-{mode}"))
    return f"task {i}: " + (", ".join(done) if done else "already there")


def write_card(suite: Dict[str, Any], out: Path, generator: Dict[str, Any]) -> None:
    """``dataset.json`` from the files (what ``promptdt collect`` writes for its families)."""
    import promptdt

    tasks = []
    for i, t in enumerate(suite["tasks"]):
        files = []
        for f in sorted(out.glob(f"{suite['name']}-{i}-*.safetensors")):
            ds = promptdt.load_dataset(f)
            rets = np.array([tr.episode_return for tr in ds.trajectories], np.float64)
            files.append({"name": f.name, "mode": ds.mode, "episodes": len(ds),
                          "steps": int(sum(len(tr) for tr in ds.trajectories)),
                          "returns": {"mean": float(rets.mean()), "std": float(rets.std()),
                                      "min": float(rets.min()), "max": float(rets.max())}})
        tasks.append({"index": i, "params": t["params"], "files": files})
    card = {"format": "promptdt-dataset", "format_version": "1", "env": suite["name"],
            "obs_dim": suite["obs_dim"], "act_dim": suite["act_dim"], "tasks": tasks,
            "generator": generator}
    tmp = out / ".dataset.json.tmp"
    tmp.write_text(json.dumps(card, indent=2) + "\n")
    os.replace(tmp, out / "dataset.json")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("suite", help="the suite file (push-v3.toml)")
    p.add_argument("out", help="the data directory")
    p.add_argument("--expert-episodes", type=int, default=5)
    p.add_argument("--medium-episodes", type=int, default=3)
    p.add_argument("--random-episodes", type=int, default=2)
    p.add_argument("--prompt-episodes", type=int, default=3)
    p.add_argument("--expert-noise", type=float, default=0.1)
    p.add_argument("--medium-noise", type=float, default=0.6)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=1, help="tasks collected at once (processes)")
    a = p.parse_args()
    suite_path = Path(a.suite).resolve()
    suite = tomllib.loads(suite_path.read_text())
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    args = {**vars(a), "suite": str(suite_path), "out": str(out)}
    jobs = [(args, i) for i in range(len(suite["tasks"]))]
    start = time.time()
    with Pool(a.jobs) as pool:
        for k, line in enumerate(pool.imap(collect_task, jobs), 1):
            print(f"[{time.time() - start:6.0f} s] {k}/{len(jobs)} {line}", flush=True)
    from importlib.metadata import version

    write_card(suite, out, {
        "policy": f"metaworld.policies ({mw_envs.scripted_policy(suite['environment']['kwargs']['env_name']).__class__.__name__})",
        "metaworld": version("metaworld"), "mujoco": version("mujoco"),
        "expert": f"{a.expert_episodes} episodes, Gaussian action noise std {a.expert_noise}",
        "medium": f"{a.medium_episodes} episodes, Gaussian action noise std {a.medium_noise}",
        "random": f"{a.random_episodes} episodes, uniform actions in [-1, 1]",
        "prompt": f"best:{a.prompt_episodes} (the task's episodes of highest return)",
        "seed": a.seed, "script": "examples/metaworld_ml1/collect.py"})
    print(f"collect: {out}/dataset.json written ({time.time() - start:.0f} s)")


if __name__ == "__main__":
    main()
