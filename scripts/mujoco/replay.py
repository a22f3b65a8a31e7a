#!/usr/bin/env python3
"""Python twin of promptdt's MuJoCo environments, for the Rust-vs-Python parity check.

Written from the environment description in docs/mujoco-envs.md (itself from the reference
specification, promptdt-reference.md e.1-e.3) on the official Python bindings `mujoco==3.17.0`,
the same MuJoCo build the Rust crate links. It is not the reference code (which ran on gym +
mujoco-py 2.0); it computes every quantity in the same order as the Rust environments so that the
two agree bit for bit.

Usage:
  replay.py run INPUT [-o OUTPUT]     replay one request (JSON or .npz, see below); JSON result
  replay.py fixtures [--out DIR]      regenerate testdata/mujoco/replay-{family}.json

Request (JSON): {"family": "cheetah_vel", "task": 3, "init_qpos": [9 or 15 floats],
"init_qvel": [9 or 14 floats], "actions": [[6 or 8 floats], ...]}; an .npz holds the same keys
(family as a 0-d string array). Result: {"family", "task", "observations" (steps + 1 rows),
"rewards", "terminated", "truncated", "unused_actions"}.

Needs: numpy, mujoco==3.17.0 (pip install mujoco==3.17.0).
"""
import argparse
import json
import math
import os
import sys
import tempfile

import numpy as np
import mujoco

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
ASSETS = os.path.join(ROOT, "crates", "envs", "assets")

FRAME_SKIP = 5
HORIZON = 200
# Task parameters, as the reference's task configs hold them (shared/data/official-task-parameters.json).
DIRECTIONS = [1.0, -1.0]
VELOCITIES = [float(v) for v in np.linspace(0.075, 3.0, 40)]
ANT_GOALS = [
    1.2033605945679715, 0.42663053293975295, 4.944775479235424, 4.123865140631488,
    4.005661927041337, 3.6166196447991155, 0.2454395410534735, 2.2482091824000023,
    5.941902704664186, 0.3772718531319245, 5.428936649786095, 5.512178944021152,
    0.32165928764709933, 4.099267058824251, 3.4667560926228758, 3.754286493596681,
    3.0380999478653634, 1.7780670544024204, 1.87066585880318, 3.5280645037970855,
    2.488439431116824, 4.9555527108165744, 2.629414941289294, 0.9041750006610754,
    0.9481747251390378, 0.3470916400248258, 4.511560745487209, 1.8366841068540096,
    1.2489330732603883, 5.223613581580657, 3.5687934580622827, 0.5173559024487111,
    3.42432703215533, 0.9987672483128179, 4.252223478300645, 0.7443831939965014,
    2.795992744398332, 5.579358183330077, 5.009380886994954, 0.42712294662677097,
    6.036807514750099, 4.141909635790574, 4.516203325267859, 4.672030605450681,
    5.577812002817041, 0.8416054504725834, 4.881875268913003, 5.26525595696687,
    5.210675507763471, 0.1831988121347493,
]


def sq_norm(action):
    """||a||^2 summed in float64, in coordinate order (as the Rust `action_sq_norm`)."""
    s = 0.0
    for v in action:
        v = float(v)
        s += v * v
    return s


class Env:
    """One task of cheetah_dir, cheetah_vel or ant_dir (contact cost as the reference: zero)."""

    def __init__(self, family, task, contact_cost="reference"):
        self.family, self.task = family, int(task)
        n_tasks = {"cheetah_dir": 2, "cheetah_vel": 40, "ant_dir": 50}.get(family)
        if n_tasks is None:
            raise ValueError(f"unknown family {family!r}")
        if not 0 <= self.task < n_tasks:
            raise ValueError(f"unknown task {task} of {family} (0..{n_tasks})")
        xml = "ant_dir.xml" if family == "ant_dir" else "half_cheetah.xml"
        with open(os.path.join(ASSETS, xml)) as f:
            self.model = mujoco.MjModel.from_xml_string(f.read())
        self.data = mujoco.MjData(self.model)
        self.torso = self.model.body("torso").id
        self.dt = self.model.opt.timestep * FRAME_SKIP
        self.contact_cost = contact_cost
        self.t = 0

    def reset_to(self, qpos, qvel):
        d = self.data
        mujoco.mj_resetData(self.model, d)
        d.qpos[:] = np.asarray(qpos, dtype=np.float64)
        d.qvel[:] = np.asarray(qvel, dtype=np.float64)
        mujoco.mj_forward(self.model, d)  # fresh kinematics at reset
        self.t = 0
        return self.obs()

    def obs(self):
        d = self.data
        if self.family == "ant_dir":
            parts = [d.qpos[2:], d.qvel]
        else:
            # xpos as mj_step left it: one sub-step stale after a step (no mj_forward here).
            parts = [d.qpos[1:], d.qvel, d.xpos[self.torso]]
        return np.concatenate(parts).astype(np.float32)

    def step(self, action):
        action = np.asarray(action, dtype=np.float32)
        d = self.data
        x_before = float(d.qpos[0])
        p_before = d.xpos[self.torso].copy()
        d.ctrl[:] = action.astype(np.float64)
        for _ in range(FRAME_SKIP):
            mujoco.mj_step(self.model, d)
        x_after = float(d.qpos[0])
        p_after = d.xpos[self.torso].copy()
        terminated = False
        if self.family == "cheetah_dir":
            reward = DIRECTIONS[self.task] * ((x_after - x_before) / self.dt) - 0.05 * sq_norm(action)
        elif self.family == "cheetah_vel":
            v = (x_after - x_before) / self.dt
            reward = -abs(v - VELOCITIES[self.task]) - 0.05 * sq_norm(action)
        else:
            contact = 0.0
            if self.contact_cost == "computed":
                mujoco.mj_rnePostConstraint(self.model, d)
                contact = 0.5e-3 * float(np.sum(np.square(np.clip(d.cfrc_ext, -1.0, 1.0))))
            g = ANT_GOALS[self.task]
            vx = (float(p_after[0]) - float(p_before[0])) / self.dt
            vy = (float(p_after[1]) - float(p_before[1])) / self.dt
            forward = vx * math.cos(g) + vy * math.sin(g)
            reward = forward - 0.5 * sq_norm(action) - contact + 1.0
            state = np.concatenate([d.qpos, d.qvel])
            z = float(d.qpos[2])
            terminated = not (np.isfinite(state).all() and 0.2 <= z <= 1.0)
        self.t += 1
        truncated = (not terminated) and self.t >= HORIZON
        return self.obs(), np.float32(reward), terminated, truncated


def replay(family, task, init_qpos, init_qvel, actions):
    env = Env(family, task)
    observations = [env.reset_to(init_qpos, init_qvel)]
    rewards, terms, truncs, unused = [], [], [], 0
    for t, a in enumerate(actions):
        o, r, term, trunc = env.step(a)
        observations.append(o)
        rewards.append(r)
        terms.append(term)
        truncs.append(trunc)
        if term or trunc:
            unused = len(actions) - t - 1
            break
    return {"family": family, "task": int(task), "observations": observations, "rewards": rewards,
            "terminated": terms, "truncated": truncs, "unused_actions": unused}


def to_json(value):
    """JSON text; float32 values in their shortest round-trip form, float64 in Python's repr."""
    if isinstance(value, dict):
        return "{" + ",".join(json.dumps(k) + ":" + to_json(v) for k, v in value.items()) + "}"
    if isinstance(value, np.ndarray):
        return to_json(list(value))
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(to_json(v) for v in value) + "]"
    if isinstance(value, np.float32):
        if not np.isfinite(value):
            raise ValueError("non-finite value")
        return str(value)  # numpy's shortest repr that reads back to the same float32
    if isinstance(value, (np.floating, float)):
        return repr(float(value))
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return json.dumps(value)


def load_request(path):
    if path.endswith(".npz"):
        z = np.load(path)
        return (str(z["family"]), int(z["task"]), z["init_qpos"].astype(np.float64),
                z["init_qvel"].astype(np.float64), z["actions"].astype(np.float32))
    with open(path) as f:
        r = json.load(f)
    return (r["family"], r["task"], np.array(r["init_qpos"], dtype=np.float64),
            np.array(r["init_qvel"], dtype=np.float64), np.array(r["actions"], dtype=np.float32))


# Fixture cases per family: (task, steps, action bound). The third goes beyond the ctrlrange
# [-1, 1], which MuJoCo clamps while the reward charges the raw action.
FIXTURE_CASES = {
    "cheetah_dir": [(0, 200, 1.0), (1, 50, 1.0), (1, 50, 1.5)],
    "cheetah_vel": [(2, 200, 1.0), (17, 50, 1.0), (39, 50, 1.5)],
    "ant_dir": [(0, 200, 1.0), (6, 50, 1.0), (41, 50, 1.5)],
}
FIXTURE_SEED = 20220706


def fixtures(out_dir):
    os.makedirs(out_dir, exist_ok=True)
    rng = np.random.default_rng(FIXTURE_SEED)
    for family, cases in FIXTURE_CASES.items():
        out = []
        for task, steps, bound in cases:
            env = Env(family, task)
            nq, nv, nu = env.model.nq, env.model.nv, env.model.nu
            init_qpos = env.model.qpos0 + rng.uniform(-0.1, 0.1, nq)
            init_qvel = 0.1 * rng.standard_normal(nv)
            actions = rng.uniform(-bound, bound, (steps, nu)).astype(np.float32)
            result = replay(family, task, init_qpos, init_qvel, actions)
            out.append({"task": task, "init_qpos": [float(v) for v in init_qpos],
                        "init_qvel": [float(v) for v in init_qvel], "actions": actions,
                        "expected": {k: result[k] for k in
                                     ("observations", "rewards", "terminated", "truncated", "unused_actions")}})
        doc = {"generator": "scripts/mujoco/replay.py fixtures", "mujoco": mujoco.mj_versionString(),
               "numpy_seed": FIXTURE_SEED, "family": family, "cases": out}
        path = os.path.join(out_dir, f"replay-{family}.json")
        with open(path, "w") as f:
            f.write(to_json(doc) + "\n")
        print(f"wrote {path} ({os.path.getsize(path) / 1e3:.0f} kB)", file=sys.stderr)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    run = sub.add_parser("run", help="replay one request")
    run.add_argument("input")
    run.add_argument("-o", "--output", help="result file (default: stdout)")
    fx = sub.add_parser("fixtures", help="regenerate the parity fixtures")
    fx.add_argument("--out", default=os.path.join(ROOT, "testdata", "mujoco"))
    args = ap.parse_args()
    for name in ("input", "output", "out"):
        if getattr(args, name, None):
            setattr(args, name, os.path.abspath(getattr(args, name)))
    # MuJoCo appends its warnings (gym's half_cheetah.xml triggers one per load) to MUJOCO_LOG.TXT
    # in the working directory: keep that out of the checkout.
    os.chdir(tempfile.gettempdir())
    if args.cmd == "fixtures":
        fixtures(args.out)
    else:
        result = replay(*load_request(args.input))
        text = to_json(result) + "\n"
        if args.output:
            with open(args.output, "w") as f:
                f.write(text)
        else:
            sys.stdout.write(text)


if __name__ == "__main__":
    main()
