#!/usr/bin/env python3
"""Python twin of promptdt's `metaworld_reach` environment, for the Rust-vs-Python parity check.

Written from the environment description (docs/metaworld-reach.md, itself from
shared/reference/metaworld-reach.md sec. 2) on the raw Python bindings `mujoco==3.17.0`, the same
MuJoCo build the Rust crate links, with Meta-World's own scene (scripts/fetch_metaworld.py). It is
not Meta-World's code; it computes every quantity in the same order as the Rust environment
(crates/envs/src/metaworld_reach.rs) so that the two agree bit for bit. The `check` command runs
the same requests through the real `metaworld==3.1.1` `reach-v3` (reward version v2) and requires
bitwise equality with the twin, so the chain is Rust == twin == Meta-World.

Usage:
  replay.py fixtures [--out DIR]   regenerate testdata/metaworld/{replay-reach,tasks-reach}.json
  replay.py check [--fixtures DIR] replay the fixtures' requests through real metaworld 3.1.1 and
                                   the twin; compare bitwise (needs metaworld, gymnasium, scipy)
  replay.py bench [--steps N]      env steps/s of the twin and of metaworld reach-v3 (1 env)

Needs: numpy and mujoco==3.17.0; `check` and `bench` also metaworld==3.1.1 (install with
--no-deps: it pins mujoco==3.3.0), gymnasium>=1.1, scipy, imageio and packaging. Example scratch
venv, outside the repository:
  python3 -m venv /tmp/mwvenv
  /tmp/mwvenv/bin/pip install mujoco==3.17.0 gymnasium==1.4.0 scipy numpy imageio packaging
  /tmp/mwvenv/bin/pip install --no-deps metaworld==3.1.1
"""
import argparse
import base64
import json
import math
import os
import platform
import sys
import tempfile
import time

# np.linalg.norm of a 3-vector is a BLAS ddot: OpenBLAS's Haswell/Zen/Sandybridge kernels sum
# x*x + y*y + z*z left to right, its SkylakeX (AVX-512) kernel with fused multiply-adds, which
# changes the reward in the last bit now and then. So metaworld itself is CPU-dependent there. The
# twin and the Rust environment use the plain sum; pin the kernel that computes it before numpy
# loads OpenBLAS, unless the caller chose one (`check --native-blas` reports the difference).
if platform.machine() in ("x86_64", "AMD64") and "--native-blas" not in sys.argv:
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

import numpy as np
import mujoco

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
SCENE = os.path.join(ROOT, "third_party", "metaworld", "assets", "sawyer_xyz", "sawyer_reach_v3.xml")

FRAME_SKIP = 5
HORIZON = 500
HAND_INIT_POS = np.array([0.0, 0.6, 0.2])
HAND_LOW = np.array([-0.5, 0.40, 0.05])
HAND_HIGH = np.array([0.5, 1.0, 0.5])
# Meta-World's `_HAND_SPACE`: the observation clip bounds of the hand (a no-op for reach, kept).
HAND_SPACE_LOW = np.array([-0.525, 0.348, -0.0525])
HAND_SPACE_HIGH = np.array([0.525, 1.025, 0.7])
GOAL_LOW = np.array([-0.1, 0.8, 0.05])
GOAL_HIGH = np.array([0.1, 0.9, 0.3])
RESET_LOW = np.array([-0.1, 0.6, 0.02, -0.1, 0.8, 0.05])
RESET_HIGH = np.array([0.1, 0.7, 0.02, 0.1, 0.9, 0.3])
MOCAP_QUAT = np.array([1.0, 0.0, 1.0, 0.0])
# metaworld 3.x weld: anchor 0, relpos 0, relquat (-1, 0, 0, 0), torquescale 5. MuJoCo 3.17 has a
# 12th eq_data field (mjNEQDATA = 12); like the patched metaworld, only the first 11 are written.
WELD_EQ_DATA = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0]
TARGET_RADIUS = 0.05
ACTION_SCALE = np.float32(0.01)


def norm3(v):
    """sqrt(x^2 + y^2 + z^2) summed left to right (np.linalg.norm agreed bitwise on 3-vectors)."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return math.sqrt(x * x + y * y + z * z)


def quat_from_matrix(m):
    """scipy 1.17 `Rotation.from_matrix(m).as_quat()` (x, y, z, w) for a proper rotation matrix."""
    m = [[float(m[3 * i + j]) for j in range(3)] for i in range(3)]
    tr = m[0][0] + m[1][1] + m[2][2]
    cands = [m[0][0], m[1][1], m[2][2], tr]
    c = max(range(4), key=lambda k: (cands[k], -k))  # first maximum
    if c == 3:
        q = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1.0 + tr]
    else:
        i, j = c, (c + 1) % 3
        k = (j + 1) % 3
        q = [0.0] * 4
        q[i] = 1.0 - tr + 2.0 * m[i][i]
        q[j] = m[j][i] + m[i][j]
        q[k] = m[k][i] + m[i][k]
        q[3] = m[k][j] - m[j][k]
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return [v / n for v in q]


def tolerance_long_tail(d, margin):
    """Meta-World's reward_utils.tolerance(d, bounds=(0, 0.05), margin, 'long_tail', 0.1)."""
    if 0.0 <= d <= TARGET_RADIUS:
        return 1.0
    x = (d - TARGET_RADIUS) / margin
    z = x * 3.0  # sqrt(1 / 0.1 - 1) is exactly 3.0
    return 1.0 / (z * z + 1.0)


def task_vectors(seed, draws_per_reset, n=50):
    """ML1's task list: `rand_vec`s from the global numpy RNG seeded with `seed`, one per reset;
    each reset runs `draws_per_reset` rejection loops (legacy reach-v2: 1; metaworld 3.x: 2, of
    which the last is recorded)."""
    rng = np.random.RandomState(seed)
    out = []
    for _ in range(n):
        for _ in range(draws_per_reset):
            v = rng.uniform(RESET_LOW, RESET_HIGH, size=6)
            while np.linalg.norm(v[:2] - v[3:5]) < 0.15:
                v = rng.uniform(RESET_LOW, RESET_HIGH, size=6)
        out.append(v)
    assert len({tuple(v) for v in out}) == n
    return out


def expert_action(hand, goal):
    """SawyerReachV3Policy: [5 (goal - hand), 0] in float64, stored as float32."""
    a = np.zeros(4, dtype=np.float32)
    a[:3] = 5.0 * (np.asarray(goal, dtype=np.float64) - np.asarray(hand, dtype=np.float64))
    return a


class Reach:
    """One reach task: `rand_vec` = obj xyz | goal xyz; goal shown in the obs or zeroed (ML1)."""

    def __init__(self, rand_vec, goal_visible):
        self.model = mujoco.MjModel.from_xml_path(SCENE)
        self.model.eq_data[0, :11] = WELD_EQ_DATA
        self.data = mujoco.MjData(self.model)
        self.rand_vec = np.asarray(rand_vec, dtype=np.float64)
        self.goal = self.rand_vec[3:6].copy()
        self.goal_visible = bool(goal_visible)
        self.margin = norm3(HAND_INIT_POS - self.goal)
        m = self.model
        self.hand = m.body("hand").id
        self.rclaw, self.lclaw = m.body("rightclaw").id, m.body("leftclaw").id
        self.obj = m.body("obj").id
        self.obj_geom = m.geom("objGeom").id
        self.rsite, self.lsite = m.site("rightEndEffector").id, m.site("leftEndEffector").id
        self.t = 0
        self.prev = None

    def frame(self):
        d = self.data
        hand = d.xpos[self.hand].copy()
        grip = min(max(norm3(d.xpos[self.rclaw] - d.xpos[self.lclaw]) / 0.1, 0.0), 1.0)
        f = np.zeros(18)
        f[0:3] = hand
        f[3] = grip
        f[4:7] = d.xpos[self.obj]
        f[7:11] = quat_from_matrix(d.geom_xmat[self.obj_geom])
        return f

    def obs(self, cur):
        goal = self.goal if self.goal_visible else np.zeros(3)
        return np.concatenate([cur, self.prev, goal])

    def tcp(self):
        return (self.data.site_xpos[self.rsite] + self.data.site_xpos[self.lsite]) / 2.0

    def reset(self):
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        for _ in range(50):
            d.mocap_pos[0] = HAND_INIT_POS
            d.mocap_quat[0] = MOCAP_QUAT
            d.ctrl[:] = [-1.0, 1.0]
            for _ in range(FRAME_SKIP):
                mujoco.mj_step(m, d)
        d.qpos[9:12] = self.rand_vec[0:3]
        d.qvel[9:15] = 0.0
        mujoco.mj_forward(m, d)
        cur = self.frame()
        self.prev = cur
        self.t = 0
        return self.obs(cur)

    def step(self, action):
        a = np.asarray(action, dtype=np.float32)
        assert a.shape == (4,) and np.isfinite(a).all()
        if self.t >= HORIZON:
            raise ValueError("episode over")
        m, d = self.model, self.data
        delta = np.clip(a[:3], np.float32(-1), np.float32(1)) * ACTION_SCALE  # float32 product
        d.mocap_pos[0] = np.clip(d.mocap_pos[0] + delta.astype(np.float64), HAND_LOW, HAND_HIGH)
        d.mocap_quat[0] = MOCAP_QUAT
        d.ctrl[:] = [float(a[3]), float(-a[3])]
        for _ in range(FRAME_SKIP):
            mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)  # metaworld 3.x: fresh kinematics for obs and reward
        self.t += 1
        cur = self.frame()
        obs = self.obs(cur)
        self.prev = cur
        # Meta-World's observation-space clip (hand and gripper bounds; a no-op in practice).
        for base in (0, 18):
            obs[base:base + 3] = np.clip(obs[base:base + 3], HAND_SPACE_LOW, HAND_SPACE_HIGH)
            obs[base + 3] = min(max(obs[base + 3], -1.0), 1.0)
        dist = norm3(self.tcp() - self.goal)
        reward = 10.0 * tolerance_long_tail(dist, self.margin)
        success = dist <= TARGET_RADIUS
        return obs, reward, success, self.t == HORIZON


# ---------------------------------------------------------------------------------------------
# Fixtures


def fnv1a64(data, h=0xCBF29CE484222325):
    for b in data:
        h ^= b
        h = (h * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return h


def step_digest(obs, reward, success, truncated):
    """FNV-1a 64 of the step's bits: 39 obs f64 LE, reward f64 LE, success and truncated bytes."""
    blob = np.asarray(obs, dtype="<f8").tobytes() + np.float64(reward).astype("<f8").tobytes()
    blob += bytes([int(bool(success)), int(bool(truncated))])
    return f"{fnv1a64(blob):016x}"


def reset_digest(obs):
    return f"{fnv1a64(np.asarray(obs, dtype='<f8').tobytes()):016x}"


def f32_b64(actions):
    return base64.b64encode(np.asarray(actions, dtype="<f4").tobytes()).decode()


def f32_from_b64(text):
    return np.frombuffer(base64.b64decode(text), dtype="<f4").reshape(-1, 4).copy()


# (ML1 train-task index of the legacy seed-1 list, goal visible, policy, steps). Tasks cover a low
# goal (18: z 0.081), a far-y goal (5: y 0.899) and ordinary ones; 500 steps check truncation.
FIXTURE_CASES = [
    (1, False, "expert", 500),
    (18, True, "expert", 500),
    (5, False, "expert_noise", 500),
    (20, True, "expert_noise", 500),
    (9, False, "uniform", 500),
    (13, True, "saturate", 500),
]
FIXTURE_SEED = 20220614
NOISE_PCT = 0.1  # Meta-World's test harness: a ~ N(a, (pct * 2)^2) per dimension
FULL_OBS_STEPS = sorted(set(list(range(6)) + list(range(50, 501, 50)) + [499]))


def saturating_actions(steps):
    """Six phases (+x, -x, +y, -y, +z, -z) at 1.5 x the action bound, gripper at +-2: drives the
    mocap into every face of its box and the gripper ctrl beyond its range."""
    out = np.zeros((steps, 4), dtype=np.float32)
    for t in range(steps):
        phase = (t * 6) // steps
        out[t, phase // 2] = 1.5 if phase % 2 == 0 else -1.5
        out[t, 3] = 2.0 if phase % 2 == 0 else -2.0
    return out


def run_case(rand_vec, visible, policy, steps, rng):
    env = Reach(rand_vec, visible)
    obs0 = env.reset()
    observations, rewards, successes, truncs, actions = [obs0], [], [], [], []
    fixed = None
    if policy == "uniform":
        fixed = rng.uniform(-1.5, 1.5, (steps, 4)).astype(np.float32)
    elif policy == "saturate":
        fixed = saturating_actions(steps)
    obs = obs0
    for t in range(steps):
        if fixed is not None:
            a = fixed[t]
        else:
            a = expert_action(obs[0:3], env.goal)  # the true goal, also when the obs hides it
            if policy == "expert_noise":
                a = rng.normal(a, NOISE_PCT * 2.0).astype(np.float32)
        obs, r, s, tr = env.step(a)
        actions.append(a)
        observations.append(obs)
        rewards.append(r)
        successes.append(s)
        truncs.append(tr)
    return {"observations": observations, "rewards": rewards, "success": successes,
            "truncated": truncs, "actions": np.array(actions, dtype=np.float32)}


def fixture_case(task, visible, policy, steps, rand_vec, run):
    return {
        "task": task, "goal_visible": visible, "policy": policy, "rand_vec": [float(v) for v in rand_vec],
        "actions_f32_b64": f32_b64(run["actions"]),
        "expected": {
            "reset_digest": reset_digest(run["observations"][0]),
            "step_digests": [step_digest(o, r, s, tr) for o, r, s, tr in
                             zip(run["observations"][1:], run["rewards"], run["success"], run["truncated"])],
            "rewards": [float(r) for r in run["rewards"]],
            "success": "".join("1" if s else "0" for s in run["success"]),
            "truncated": "".join("1" if s else "0" for s in run["truncated"]),
            "full_observations": {str(t): [float(v) for v in run["observations"][t]]
                                  for t in FULL_OBS_STEPS if t < len(run["observations"])},
        },
    }


def write_json(path, doc):
    with open(path, "w") as f:
        json.dump(doc, f, separators=(",", ":"))
        f.write("\n")
    print(f"wrote {path} ({os.path.getsize(path) / 1e3:.0f} kB)", file=sys.stderr)


def fixtures(out_dir):
    os.makedirs(out_dir, exist_ok=True)
    lists = {
        "legacy_seed1": task_vectors(1, 1), "legacy_seed2": task_vectors(2, 1),
        "v3_seed1": task_vectors(1, 2), "v3_seed2": task_vectors(2, 2),
    }
    write_json(os.path.join(out_dir, "tasks-reach.json"), {
        "generator": "scripts/metaworld/replay.py fixtures", "numpy": np.__version__,
        "note": "ML1 reach task vectors (obj xyz | goal xyz); legacy = 1 draw loop per reset "
                "(ML1('reach-v2', seed) of 2021), v3 = 2 (metaworld 3.x ML1('reach-v3', seed))",
        "lists": {k: [[float(x) for x in v] for v in vs] for k, vs in lists.items()},
    })
    rng = np.random.default_rng(FIXTURE_SEED)
    cases = []
    for task, visible, policy, steps in FIXTURE_CASES:
        rand_vec = lists["legacy_seed1"][task]
        run = run_case(rand_vec, visible, policy, steps, rng)
        cases.append(fixture_case(task, visible, policy, steps, rand_vec, run))
        print(f"task {task} {policy}: return {sum(run['rewards']):.1f}, "
              f"success at end {run['success'][-1]}", file=sys.stderr)
    write_json(os.path.join(out_dir, "replay-reach.json"), {
        "generator": "scripts/metaworld/replay.py fixtures", "mujoco": mujoco.mj_versionString(),
        "numpy_seed": FIXTURE_SEED, "noise_pct": NOISE_PCT, "cases": cases,
    })


# ---------------------------------------------------------------------------------------------
# Real Meta-World


def patch_metaworld():
    """The one patch metaworld 3.1.1 needs on MuJoCo 3.17: a weld has 12 eq_data numbers there
    (mjNEQDATA = 12), metaworld assigns 11 (and crashes); write the same 11, keep the 12th."""
    from metaworld.sawyer_xyz_env import SawyerMocapBase

    def reset_mocap_welds(self):
        if self.model.nmocap > 0 and self.model.eq_data is not None:
            for i in range(self.model.eq_data.shape[0]):
                if self.model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
                    self.model.eq_data[i, :11] = np.array(WELD_EQ_DATA)

    SawyerMocapBase.reset_mocap_welds = reset_mocap_welds


def metaworld_env(rand_vec, visible):
    """metaworld 3.1.1 reach-v3 (reward v2) with the task frozen to `rand_vec`, as ML1/MT1 set it."""
    import pickle
    import metaworld
    from metaworld.envs.sawyer_reach_v3 import SawyerReachEnvV3

    patch_metaworld()
    env = SawyerReachEnvV3(reward_function_version="v2")
    data = {"rand_vec": np.array(rand_vec, dtype=np.float64), "env_cls": SawyerReachEnvV3,
            "partially_observable": not visible}
    env.set_task(metaworld.Task(env_name="reach-v3", data=pickle.dumps(data)))
    return env


def numpy_norm_kind():
    """'plain' if np.linalg.norm of 3-vectors equals the twin's left-to-right sum here."""
    rng = np.random.default_rng(0)
    plain = 0
    for _ in range(2000):
        v = rng.normal(size=3)
        plain += float(np.linalg.norm(v)) == norm3(v)
    return "plain" if plain == 2000 else "other"


def check(fixture_dir, native_blas):
    import metaworld
    from metaworld.policies.sawyer_reach_v3_policy import SawyerReachV3Policy

    patch_metaworld()
    kind = numpy_norm_kind()
    print(f"OPENBLAS_CORETYPE={os.environ.get('OPENBLAS_CORETYPE', '(unset)')}: np.linalg.norm sums "
          f"3-vectors {'left to right, as the twin' if kind == 'plain' else 'not as the twin'}")
    if kind != "plain" and not native_blas:
        sys.exit("numpy's BLAS does not sum like the twin; rerun with OPENBLAS_CORETYPE=Haswell")
    # Task lists: the v3 ones against metaworld's own ML1 (the legacy ones cannot be: no PyPI
    # release has the 2021 code; they come from the same generator with one draw loop per reset).
    with open(os.path.join(fixture_dir, "tasks-reach.json")) as f:
        lists = json.load(f)["lists"]
    import pickle
    for seed, key in ((1, "v3_seed1"), (2, "v3_seed2")):
        ml1 = metaworld.ML1("reach-v3", seed=seed)
        got = [pickle.loads(t.data)["rand_vec"] for t in ml1.train_tasks]
        want = np.array(lists[key])
        assert np.array_equal(np.array(got), want) and np.array(got).tobytes() == want.tobytes(), key
        print(f"ML1('reach-v3', seed={seed}).train_tasks == {key}: 50 vectors bitwise equal")

    with open(os.path.join(fixture_dir, "replay-reach.json")) as f:
        doc = json.load(f)
    policy = SawyerReachV3Policy()
    total_steps = 0
    reward_diffs, grip_diffs = [], []
    for c, case in enumerate(doc["cases"]):
        actions = f32_from_b64(case["actions_f32_b64"])
        twin = Reach(case["rand_vec"], case["goal_visible"])
        env = metaworld_env(case["rand_vec"], case["goal_visible"])
        o_mw, _ = env.reset()
        o_tw = twin.reset()
        assert o_mw.tobytes() == o_tw.tobytes(), f"case {c}: reset obs differ"
        assert reset_digest(o_mw) == case["expected"]["reset_digest"], f"case {c}: reset digest"
        ret = 0.0
        for t, a in enumerate(actions):
            if case["policy"] == "expert":
                full = o_mw.copy()
                full[36:39] = env._target_pos  # the policy reads the true goal
                pa = policy.get_action(full)
                assert pa.dtype == np.float32 and pa.tobytes() == a.tobytes(), f"case {c} step {t}: policy"
            o_mw, r_mw, term, trunc, info = env.step(a)
            o_tw, r_tw, s_tw, tr_tw = twin.step(a)
            where = f"case {c} ({case['policy']}) step {t}"
            if native_blas:  # the gripper opening (obs 3, and 21 a step later) is a norm too
                diff = o_mw[[3, 21]] - o_tw[[3, 21]]
                grip_diffs.extend(float(abs(d)) for d in diff if d != 0.0)
                o_tw = o_tw.copy()
                o_tw[[3, 21]] = o_mw[[3, 21]]
            if o_mw.tobytes() != o_tw.tobytes():
                i = int(np.flatnonzero(o_mw != o_tw)[0])
                raise AssertionError(f"{where}: obs[{i}] metaworld {o_mw[i]!r} twin {o_tw[i]!r}")
            if np.float64(r_mw).tobytes() != np.float64(r_tw).tobytes():
                if not native_blas:
                    raise AssertionError(f"{where}: reward {r_mw!r} vs {r_tw!r}")
                reward_diffs.append(abs(float(r_mw) - r_tw) / r_tw)
            assert bool(info["success"]) == s_tw and trunc == tr_tw and not term, f"{where}: flags"
            if not native_blas:
                assert step_digest(o_mw, r_mw, info["success"], trunc) == \
                    case["expected"]["step_digests"][t], f"{where}: fixture digest"
            ret += r_mw
        total_steps += len(actions)
        print(f"case {c}: task {case['task']} visible={case['goal_visible']} {case['policy']}: "
              f"{len(actions)} steps {'matched' if native_blas else 'bitwise equal (metaworld == twin == fixture)'}, "
              f"return {ret:.4f}, "
              f"final success {bool(info['success'])}, truncated {trunc}")
    if native_blas:
        print(f"native BLAS: flags, expert actions and observations other than the gripper opening "
              f"bitwise equal; rewards differ on {len(reward_diffs)} of {total_steps} steps, by at most "
              f"{max(reward_diffs, default=0.0):.2e} relative; gripper values differ {len(grip_diffs)} "
              f"times, by at most {max(grip_diffs, default=0.0):.2e}")
    else:
        print(f"all {len(doc['cases'])} cases, {total_steps} steps: metaworld 3.1.1 reach-v3 == twin, bitwise")


def bench(steps):
    rand_vec = task_vectors(1, 1)[1]
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, 4)).astype(np.float32)
    for name, make in (("twin (raw mujoco)", lambda: Reach(rand_vec, False)),
                       ("metaworld 3.1.1 reach-v3", lambda: metaworld_env(rand_vec, False))):
        env = make()
        env.reset()
        t0 = time.perf_counter()
        n = 0
        for a in actions:
            out = env.step(a)
            n += 1
            if out[3]:  # truncated (index 3 in both the twin's 4-tuple and gymnasium's 5-tuple)
                env.reset()
        dt = time.perf_counter() - t0
        print(f"{name}: {n} steps (random actions, reset every {HORIZON}) in {dt:.2f} s = "
              f"{n / dt:.0f} steps/s")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    fx = sub.add_parser("fixtures", help="regenerate the parity fixtures")
    fx.add_argument("--out", default=os.path.join(ROOT, "testdata", "metaworld"))
    ck = sub.add_parser("check", help="twin vs real metaworld on the fixtures' requests")
    ck.add_argument("--fixtures", default=os.path.join(ROOT, "testdata", "metaworld"))
    ck.add_argument("--native-blas", action="store_true",
                    help="keep numpy's own BLAS kernel; report reward differences instead of failing")
    bn = sub.add_parser("bench", help="env steps/s, twin and metaworld")
    bn.add_argument("--steps", type=int, default=5000)
    args = ap.parse_args()
    for name in ("out", "fixtures"):
        if getattr(args, name, None):
            setattr(args, name, os.path.abspath(getattr(args, name)))
    if not os.path.exists(SCENE):
        sys.exit(f"{SCENE} is missing: run scripts/fetch_metaworld.py")
    os.chdir(tempfile.gettempdir())  # MuJoCo may write MUJOCO_LOG.TXT to the working directory
    if args.cmd == "fixtures":
        fixtures(args.out)
    elif args.cmd == "check":
        check(args.fixtures, args.native_blas)
    else:
        bench(args.steps)


if __name__ == "__main__":
    main()
