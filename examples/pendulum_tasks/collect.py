"""Writes the suite's datasets: episodes of a heuristic swing-up controller in each task.

    python collect.py DATA_DIR [--episodes N] [--prompt-episodes N] [--seed S]

For every task of `suite.toml`, `DATA_DIR/pendulum_mass-{i}-expert.safetensors` (the training
data) and `DATA_DIR/pendulum_mass-{i}-prompt-expert.safetensors` (the prompt set: the task's best
episodes, as the reference's prompt files are), written with `promptdt.write_dataset`, which checks
them against the suite before writing.

The policy is the one thing here a user would replace with their own (a scripted controller, a
trained agent): `policy(obs, mass, rng)` below.
"""
import argparse
import math
import pathlib
import numpy as np

import promptdt
from tasks import make

try:
    import tomllib  # Python 3.11+
except ImportError:  # the package supports 3.9
    import tomli as tomllib

HERE = pathlib.Path(__file__).resolve().parent
SUITE = HERE / "suite.toml"


def policy(obs, mass, rng):
    """Energy pumping, then a PD balance near the top; knows the task's mass (an expert per task),
    with some noise so that episodes differ."""
    cos, sin, vel = (float(x) for x in obs)
    angle = math.atan2(sin, cos)  # 0 upright
    if cos > 0.85:
        # theta'' = 15 sin(theta) + 3 u / m: cancel gravity, then a PD on the angle.
        u = mass / 3 * (-(15 + 10) * angle - 3 * vel)
    else:
        energy = 0.5 * vel**2 + 15 * cos  # 15 = 3 g / (2 l): upright at rest is 15
        u = 2.0 * math.copysign(1.0, vel if vel != 0 else 1.0) * (1.0 if energy < 15 else -0.5)
    return np.clip(np.array([u + rng.normal(0, 0.3)], np.float32), -2.0, 2.0)


def episode(env, mass, rng, seed, horizon):
    obs, _ = env.reset(seed=seed)
    o, a, r = [], [], []
    for _ in range(horizon):
        act = policy(obs, mass, rng)
        o.append(obs)
        a.append(act)
        obs, rew, _term, _trunc, _ = env.step(act)
        r.append(rew)
    truncated = np.zeros(horizon, bool)
    truncated[-1] = True  # cut at the suite's horizon (Pendulum never terminates)
    return promptdt.Trajectory(
        observations=np.asarray(o, np.float32), actions=np.asarray(a, np.float32),
        rewards=np.asarray(r, np.float32), terminated=np.zeros(horizon, bool), truncated=truncated)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", type=pathlib.Path)
    p.add_argument("--episodes", type=int, default=8, help="episodes per task in the dataset")
    p.add_argument("--prompt-episodes", type=int, default=3, help="episodes per task in the prompt set")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    suite = tomllib.loads(SUITE.read_text())
    a.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(a.seed)
    for i, task in enumerate(suite["tasks"]):
        env, mass = make(task["params"]), task["params"]["mass"]
        trajs = [episode(env, mass, rng, 1000 * i + e, suite["max_ep_len"]) for e in range(a.episodes)]
        best = sorted(trajs, key=lambda t: -t.episode_return)[: a.prompt_episodes]
        for mode, chosen in [("expert", trajs), ("prompt-expert", best)]:
            ds = promptdt.Dataset(obs_dim=3, act_dim=1, env=str(SUITE), task=i, mode=mode, trajectories=chosen)
            promptdt.write_dataset(a.out / f"{suite['name']}-{i}-{mode}.safetensors", ds)
        returns = [t.episode_return for t in trajs]
        print(f"task {i} ({task['name']}): {len(trajs)} episodes, return {np.mean(returns):.1f} "
              f"(best {max(returns):.1f})")


if __name__ == "__main__":
    main()
