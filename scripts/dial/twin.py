#!/usr/bin/env python3
"""Python twin of promptdt's reconstructed `dial` environment (docs/dial.md), on the raw Python
bindings `mujoco==3.17.0`, the build the Rust crate links. It computes every quantity in the same
order as crates/envs/src/dial.rs, so that the two agree bit for bit; crates/envs/tests/it/dial_parity.rs
replays the fixtures this script writes and requires equal observations, rewards and flags.

Usage:
  twin.py targets [--out FILE]   compute the hover/press/init joint poses by inverse kinematics
                                 (writes crates/envs/assets/dial/targets.json)
  twin.py fixtures [--out DIR]   regenerate testdata/dial/replay-dial.json
  twin.py expert [--episodes N]  expert success rate and episode lengths per digit
  twin.py bench [--steps N]      env steps/s of the twin (1 env)
  twin.py lengths DIR            expert episode lengths per digit of a collected dataset, beside
                                 the original's (needs safetensors)

Needs numpy and mujoco==3.17.0 (`targets` also scipy). Scratch venv, outside the repository:
  python3 -m venv /tmp/mjvenv && /tmp/mjvenv/bin/pip install mujoco==3.17.0 numpy scipy
"""
import argparse
import base64
import json
import math
import os
import random
import sys
import time

import mujoco
import numpy as np

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
SCENE = os.path.join(ROOT, "crates", "envs", "assets", "dial", "dial.xml")
TARGETS = os.path.join(ROOT, "crates", "envs", "assets", "dial", "targets.json")

ACTION_REPEAT = 20
HORIZON = 200
SUCCESS_L1 = 0.1
# The original's action box (shared/reference/dial.md sec. 2.4), in our joint convention.
C_HIGH = [0.07, 0.6, 0.07, 0.05, 0.07, 0.065, 0.07, 0.07, 0.07]
C_LOW = [-0.07, -1.0, -0.134, -0.05, -0.07, -0.065, -0.07, -0.07, -0.07]
# The original PI controller (sec. 3.1).
KP = [8.5 * k for k in (0.5, 2.5, 0.9, 0.9, 0.9, 1.0, 1.0, 1.0, 1.0)]
KI = [0.1 * k for k in (0.001, 0.001, 0.001, 0.005, 0.005, 0.001, 0.001, 0.001, 0.001)]
PI_MEMORY = 200
SETTLE_TOL = 0.03
SETTLE_MAX = 1000
FINGER_HOLD = 0.68
TWO_PI = 2.0 * math.pi


def wrap(x):
    """x wrapped to [-pi, pi): the original's `(x + pi) % (2 pi) - pi` (Python's float modulo)."""
    return math.fmod(math.fmod(x + math.pi, TWO_PI) + TWO_PI, TWO_PI) - math.pi


def clip_box(a):
    return [min(max(a[j], C_LOW[j]), C_HIGH[j]) for j in range(9)]


class PI:
    """The original's joint-space PI controller: a = KP*e + KI*S, S the scalar sum of every entry
    of the last <= 200 error vectors (before this one), clipped to the action box."""

    def __init__(self):
        self.memory = []

    def act(self, q, target):
        e = [wrap(target[j] - q[j]) for j in range(9)]
        s = 0.0
        for v in self.memory:
            for x in v:
                s += x
        a = [KP[j] * e[j] + KI[j] * s for j in range(9)]
        self.memory.append(e)
        if len(self.memory) > PI_MEMORY:
            self.memory.pop(0)
        return clip_box(a)


def load_targets():
    with open(TARGETS) as f:
        t = json.load(f)
    return t


class DialEnv:
    def __init__(self, digit, targets=None):
        self.model = mujoco.MjModel.from_xml_path(SCENE)
        self.data = mujoco.MjData(self.model)
        self.t = load_targets() if targets is None else targets
        self.digit = digit
        self.ee = self.model.body("b_finger_3").id
        self.press = self.t["press_xyz"]
        self.init = self.t["init"]
        self.steps = 0
        self.done = False

    def ee_pos(self):
        return [float(x) for x in self.data.xpos[self.ee]]

    def obs(self):
        q = [float(x) for x in self.data.qpos]
        p = self.ee_pos()
        out = q[:]
        for k in range(10):
            for i in range(3):
                out.append(p[i] - self.press[k][i])
        return np.array(out, dtype=np.float32)

    def reset(self, start=None):
        """Deterministic start at the init pose, or at `start` (a perturbed qpos) from which the
        PI controller settles back to the init pose; then one more step (the original's reset)."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:] = self.init if start is None else start
        mujoco.mj_forward(m, d)
        pi = PI()
        for _ in range(SETTLE_MAX):
            mujoco.mj_step(m, d)
            q = [float(x) for x in d.qpos]
            d.ctrl[:] = pi.act(q, self.init)
            err = 0.0
            for j in range(9):
                err += abs(q[j] - self.init[j])
            if err < SETTLE_TOL:
                break
        mujoco.mj_step(m, d)
        self.steps = 0
        self.done = False
        return self.obs()

    def l1(self):
        p = self.ee_pos()
        g = self.press[self.digit]
        return abs(g[0] - p[0]) + abs(g[1] - p[1]) + abs(g[2] - p[2])

    def step(self, action):
        assert not self.done
        a = clip_box([float(np.float32(x)) for x in action])
        self.data.ctrl[:] = a
        success = False
        for _ in range(ACTION_REPEAT):
            mujoco.mj_step(self.model, self.data)
            if self.l1() < SUCCESS_L1:
                success = True
                break
        self.steps += 1
        truncated = (not success) and self.steps >= HORIZON
        self.done = success or truncated
        return self.obs(), (1.0 if success else 0.0), success, truncated


class Expert:
    """PI toward the digit's hover pose, once per env step, reading q from the observation."""

    def __init__(self, digit, targets):
        self.target = targets["hover"][digit]
        self.pi = PI()

    def act(self, obs):
        q = [float(x) for x in obs[:9]]
        return self.pi.act(q, self.target)


# ------------------------------------------------------------------------------------------------
# Inverse kinematics for the hover, press and init poses
# ------------------------------------------------------------------------------------------------
KEYS = {1: (0.36, 0.21), 2: (0.50, 0.21), 3: (0.64, 0.21), 4: (0.36, 0.07), 5: (0.50, 0.07),
        6: (0.64, 0.07), 7: (0.36, -0.07), 8: (0.50, -0.07), 9: (0.64, -0.07), 0: (0.50, -0.21)}
KEY_TOP = 0.10
PRESS_CLEARANCE = 0.015
HOVER_CLEARANCE = 0.04
W_REF = float(os.environ.get("W_REF", "0.1"))
W_DOWN = float(os.environ.get("W_DOWN", "1"))
GRIP = np.array([0.0, 0.0, -0.16])  # a point between the fingers, in the hand frame


def lowest_point(m, d):
    """Lowest z of the arm's collision geoms (the hand and the fingers reach lowest)."""
    low = 1e9
    for gid in range(m.ngeom):
        b = m.geom_bodyid[gid]
        if b < m.body("b_4").id:
            continue
        pos = d.geom_xpos[gid]
        R = d.geom_xmat[gid].reshape(3, 3)
        size = m.geom_size[gid]
        t = m.geom_type[gid]
        if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
            z = pos[2] - abs(R[2, 2]) * size[1] - size[0]
        elif t == mujoco.mjtGeom.mjGEOM_BOX:
            z = pos[2] - sum(abs(R[2, i]) * size[i] for i in range(3))
        else:
            continue
        low = min(low, z)
    return low


def solve_ik(m, d, xy, clearance, q_ref, seed):
    """Joint pose (fingers at 0.68) whose grip point is over `xy`, with the hand pointing straight
    down, the lowest point `clearance` above the key top, a negative joint-2 gravity bias (the
    original's sign convention: negative torque lifts) and, among those, closest to `q_ref`
    (`None`: any). Least squares from 64 seeded random starts; then the grip height is corrected
    until the clearance is exact."""
    from scipy.optimize import least_squares

    hand = m.body("hand").id
    rng = np.random.default_rng(seed)
    ref = None if q_ref is None else np.array(q_ref[:6])

    def fit(goal, q_start):
        def res(q6):
            d.qpos[:6] = q6
            d.qpos[6:] = FINGER_HOLD
            mujoco.mj_kinematics(m, d)
            R = d.xmat[hand].reshape(3, 3)
            p = d.xpos[hand] + R @ GRIP
            reg = np.zeros(6) if ref is None else W_REF * np.array([wrap(x) for x in q6 - ref])
            return np.concatenate([100 * (p - goal), W_DOWN * (R[:, 2] - [0, 0, 1]), reg])

        sol = least_squares(res, q_start, xtol=1e-15, ftol=1e-15, gtol=1e-15)

        def res_pos(q6):  # polish: the grip point exactly, from the compromise above
            return res(q6)[:3]

        sol = least_squares(res_pos, sol.x, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        sol.fun = res(sol.x)
        q = np.array([wrap(x) for x in sol.x]) if ref is None else ref + np.array(
            [wrap(x) for x in sol.x - ref])
        d.qpos[:6] = q
        d.qpos[6:] = FINGER_HOLD
        mujoco.mj_forward(m, d)
        return q, float(np.sum(sol.fun[:3] ** 2)), float(np.sum(sol.fun ** 2)), float(d.qfrc_bias[1])

    z_grip = KEY_TOP + clearance + 0.03
    goal = np.array([xy[0], xy[1], z_grip])
    cands = [fit(goal, rng.uniform(-math.pi, math.pi, 6)) for _ in range(64)]
    ok = [c for c in cands if c[3] < 0]
    if not ok:
        raise SystemExit(f"IK: no pose over {xy} with a negative joint-2 bias")
    # The reachable pose nearest to the key (at the far corner, key 3, the arm falls short by
    # about 1 cm), then the least tilted and nearest to q_ref among the equally good.
    best_err = min(c[1] for c in ok)
    q = min((c for c in ok if c[1] < best_err + 1e-8), key=lambda c: c[2])[0]
    for _ in range(20):
        q, err, _, _ = fit(np.array([xy[0], xy[1], z_grip]), q)
        low = lowest_point(m, d)
        if abs(KEY_TOP + clearance - low) < 1e-9:
            break
        z_grip += KEY_TOP + clearance - low
    return [float(x) for x in q] + [FINGER_HOLD] * 3, float(low)


def cmd_targets(args):
    m = mujoco.MjModel.from_xml_path(SCENE)
    d = mujoco.MjData(m)
    ee = m.body("b_finger_3").id
    # The init pose first: the hand over the far -y corner beside the 0 key, as in the original
    # (its finger point at (0.57, -0.33, 0.28)); the targets are then the poses nearest to it.
    init, low_i = solve_ik(m, d, (0.60, -0.30), 0.10, None, seed=0)
    out = {"hover": [], "press": [], "press_xyz": [], "hover_lowest_z": [], "press_lowest_z": []}
    for digit in range(10):
        xy = KEYS[digit]
        press, low_p = solve_ik(m, d, xy, PRESS_CLEARANCE, init, seed=digit + 1)
        hover, low_h = solve_ik(m, d, xy, HOVER_CLEARANCE, press, seed=digit + 1)
        d.qpos[:] = press
        mujoco.mj_forward(m, d)
        out["press"].append(press)
        out["press_xyz"].append([float(x) for x in d.xpos[ee]])
        out["hover"].append(hover)
        out["press_lowest_z"].append(low_p)
        out["hover_lowest_z"].append(low_h)
    # The init pose: the hand over the far -y corner beside the 0 key, as in the original (its
    # finger point at (0.57, -0.33, 0.28)).
    out["init"] = init
    out["init_lowest_z"] = low_i
    text = json.dumps(out, indent=1)
    with open(args.out, "w") as f:
        f.write(text + "\n")
    print(f"wrote {args.out}")
    for k in range(10):
        print(k, np.round(out["press"][k][:6], 3), np.round(out["press_xyz"][k], 3))
    d.qpos[:] = init
    mujoco.mj_forward(m, d)
    print("init", np.round(init[:6], 3), np.round(d.xpos[ee], 3))


def run_expert(digit, targets, rng, amount=None, start_noise=False):
    env = DialEnv(digit, targets)
    start = None
    if start_noise:
        start = [targets["init"][j] + rng.uniform(-0.1, 0.1) for j in range(9)]
        start[0] += rng.uniform(0.0, 0.2)
        start[1] += rng.uniform(-0.2, 0.0)
    obs = env.reset(start)
    ex = Expert(digit, targets)
    if amount is None:
        amount = 0.0
    hold = rng.randint(1, 2)
    noise = [0.0] * 9
    for t in range(HORIZON):
        a = ex.act(obs)
        if amount > 0 and t % hold == 0:
            noise = [rng.gauss(0.0, abs(C_LOW[j]) * amount + (rng.uniform(0, 0.1) if j == 0 else 0.0))
                     for j in range(9)]
        ex_a = [a[j] + noise[j] for j in range(9)]
        obs, r, term, trunc = env.step(np.array(ex_a, dtype=np.float32))
        if term or trunc:
            return r, t + 1
    return 0.0, HORIZON


def cmd_expert(args):
    targets = load_targets()
    rng = random.Random(0)
    for digit in range(10):
        r0, n0 = run_expert(digit, targets, rng)
        lens, succ = [], 0
        for i in range(args.episodes):
            r, n = run_expert(digit, targets, rng, amount=rng.choice([0.0, 0.2, 0.3]),
                              start_noise=True)
            succ += r > 0
            lens.append(n)
        print(f"digit {digit}: noiseless {'ok' if r0 > 0 else 'FAIL'} {n0} steps; noisy "
              f"{succ}/{args.episodes}, median {int(np.median(lens))}, max {max(lens)}")


# ------------------------------------------------------------------------------------------------
# Fixtures for crates/envs/tests/it/dial_parity.rs
# ------------------------------------------------------------------------------------------------
def fnv1a64(data):
    h = 0xCBF29CE484222325
    for b in data:
        h ^= b
        h = (h * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return f"{h:016x}"


def obs_f64(env):
    """The observation at full precision (what the Rust env's obs_f64 holds)."""
    q = [float(x) for x in env.data.qpos]
    p = env.ee_pos()
    out = q[:]
    for k in range(10):
        for i in range(3):
            out.append(p[i] - env.press[k][i])
    return out


def step_digest(obs, reward, success, truncated):
    data = np.array(obs, dtype="<f8").tobytes() + np.array([reward], dtype="<f8").tobytes()
    return fnv1a64(data + bytes([int(success), int(truncated)]))


def run_case(digit, start, policy, rng, targets):
    env = DialEnv(digit, targets)
    env.reset(start)
    reset_obs = obs_f64(env)
    expert = Expert(digit, targets)
    amount = 0.3 if policy == "noisy_expert" else 0.0
    actions, digests, rewards, flags = [], [], [], []
    full = {"0": reset_obs}
    obs32 = env.obs()
    noise = [0.0] * 9
    for t in range(HORIZON):
        if policy in ("expert", "noisy_expert"):
            a = expert.act(obs32)
            if amount > 0:
                if t % 2 == 0:
                    noise = [rng.gauss(0.0, abs(C_LOW[j]) * amount) for j in range(9)]
                a = [a[j] + noise[j] for j in range(9)]
        elif policy == "random":
            a = [rng.uniform(1.5 * C_LOW[j], 1.5 * C_HIGH[j]) for j in range(9)]
        elif policy == "saturate":
            # Full lift and a push into the pad, alternating every 25 steps, beyond the box.
            a = [0.2, -2.0, 0.3, 0.1, -0.1, 0.1, 0.1, -0.1, 0.1] if (t // 25) % 2 == 0 else \
                [-0.2, 2.0, -0.3, -0.1, 0.1, -0.1, -0.1, 0.1, -0.1]
        a32 = np.array(a, dtype=np.float32)
        obs32, r, term, trunc = env.step(a32)
        o = obs_f64(env)
        actions.append(a32)
        digests.append(step_digest(o, r, term, trunc))
        rewards.append(r)
        flags.append((term, trunc))
        if t < 2 or term or trunc:
            full[str(t + 1)] = o
        if term or trunc:
            break
    acts = np.stack(actions).astype("<f4")
    return {
        "digit": digit,
        "policy": policy,
        "start": start,
        "actions_f32_b64": base64.b64encode(acts.tobytes()).decode(),
        "expected": {
            "reset_digest": step_digest(reset_obs, 0.0, False, False),
            "step_digests": digests,
            "rewards": rewards,
            "success": "".join("1" if f[0] else "0" for f in flags),
            "truncated": "".join("1" if f[1] else "0" for f in flags),
            "full_observations": full,
        },
    }


def cmd_fixtures(args):
    targets = load_targets()
    rng = random.Random(1234)
    cases = [run_case(d, None, "expert", rng, targets) for d in range(10)]
    for d in (1, 6):
        start = [targets["init"][j] + rng.uniform(-0.1, 0.1) for j in range(9)]
        start[0] += rng.uniform(0.0, 0.2)
        start[1] += rng.uniform(-0.2, 0.0)
        cases.append(run_case(d, start, "noisy_expert", rng, targets))
    cases.append(run_case(9, None, "random", rng, targets))
    cases.append(run_case(0, None, "saturate", rng, targets))
    out = {"mujoco": mujoco.__version__, "cases": cases}
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "replay-dial.json")
    with open(path + ".tmp", "w") as f:
        json.dump(out, f)
    os.replace(path + ".tmp", path)
    for c in cases:
        e = c["expected"]
        print(c["digit"], c["policy"], len(e["step_digests"]), "steps, success" if "1" in e["success"] else "steps")
    print(f"wrote {path}")


def cmd_bench(args):
    targets = load_targets()
    env = DialEnv(9, targets)
    env.reset()
    rng = np.random.default_rng(0)
    acts = rng.uniform(np.array(C_LOW) * 1.5, np.array(C_HIGH) * 1.5, (args.steps, 9)).astype(np.float32)
    n = 0
    t0 = time.perf_counter()
    for a in acts:
        _, _, term, trunc = env.step(a)
        n += 1
        if term or trunc:
            env.reset()
    dt = time.perf_counter() - t0
    print(json.dumps({"impl": "python-twin", "steps": n, "seconds": dt, "steps_per_s": n / dt}))


# The original's measured episode lengths (shared/reference/dial.md sec. 5.2 and 6.4: TACO's scene
# in MuJoCo 3.17, its expert through the env): deterministic, and noisy medians, digits 0..9.
ORIGINAL_DETERMINISTIC = [19, 104, 40, 36, 95, 66, 35, 108, 55, 29]
ORIGINAL_NOISY_MEDIAN = [11, 44, 30, 33, 28, 28, 31, 38, 34, 31]


def cmd_lengths(args):
    """Per digit: the noiseless expert's steps (twin), and the median / min / max episode length
    of the expert dataset in DIR (what `promptdt collect --env dial` wrote), beside the original's."""
    from safetensors.numpy import load_file

    targets = load_targets()
    rows = []
    for digit in range(10):
        _, n0 = run_expert(digit, targets, random.Random(0))
        d = load_file(os.path.join(args.dir, f"dial-{digit}-expert.safetensors"))
        s = d["episode_starts"]
        lens = np.diff(s)
        rows.append((digit, n0, ORIGINAL_DETERMINISTIC[digit], int(np.median(lens)),
                     ORIGINAL_NOISY_MEDIAN[digit], int(lens.min()), int(lens.max()), len(lens)))
    print("| digit | noiseless (ours) | noiseless (original) | noisy median (ours) | noisy median "
          "(original) | noisy min-max (ours) | episodes |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]}-{r[6]} | {r[7]} |")


def main():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("targets")
    p.add_argument("--out", default=TARGETS)
    p = sub.add_parser("fixtures")
    p.add_argument("--out", default=os.path.join(ROOT, "testdata", "dial"))
    p = sub.add_parser("bench")
    p.add_argument("--steps", type=int, default=20000)
    p = sub.add_parser("lengths")
    p.add_argument("dir")
    p = sub.add_parser("expert")
    p.add_argument("--episodes", type=int, default=20)
    args = ap.parse_args()
    {"targets": cmd_targets, "expert": cmd_expert, "fixtures": cmd_fixtures,
     "bench": cmd_bench, "lengths": cmd_lengths}[args.cmd](args)


if __name__ == "__main__":
    main()
