#!/usr/bin/env python3
"""The environment worker's cost (issue 53, Speed), one process tree (`benchmarks/16-worker.json`).

    bash scripts/install_python.sh        # a venv with the promptdt wheel and gymnasium
    .venv-promptdt/bin/python scripts/bench/bench_worker.py [--json-out benchmarks/16-worker.json]
    promptdt bench render                 # BENCHMARKS.md from the records

It makes a small task suite in a temporary directory: gymnasium's ``Pendulum-v1`` with its gravity
``g`` as the task (8 tasks, 5 trained on, 3 held out; horizon ``--horizon`` steps), writes its data
with ``promptdt.write_dataset`` (a noisy swing policy), trains Prompt-DT on it for a few gradient
steps with ``promptdt.train`` (K = 20, a 5-step prompt, one libtorch thread; no evaluation during
training), then times the run's few-shot evaluation on the held-out tasks, ``--repeats`` times
each, reporting the median and the 10th-90th percentiles (ms, wall clock, one evaluation each):

- **worker process**: ``promptdt.evaluate(run)``, what ``promptdt eval`` does: Rust plays the
  episodes and starts ``python -m promptdt.worker`` (this interpreter, the suite's
  ``[environment]``), which makes and steps the gymnasium environments, one request per vector
  step. Includes starting the worker (spawn, ``import promptdt``, gymnasium) and loading the run.
- **in-process (env=factory)**: ``promptdt.evaluate(run, env=factory)``: the same requests,
  answered by ``promptdt.worker.Session(factory)`` in this interpreter (no process, no pipe).
- **Python alone**: what a user writes without promptdt's evaluation: ``promptdt.Policy.load``
  (one thread), ``Policy.eval_plan`` for the same prompts and reset seeds, one
  ``gymnasium.make("Pendulum-v1", g=...)`` per episode, and a Python loop stepping them one by one
  with the actions of ``Policy.act`` (all episodes in one batch, as the evaluator batches them).
  Its returns are checked equal, bit for bit, to the worker's (the script stops otherwise).
- **vector steps**: the steps of the evaluation (every episode runs to the horizon: Pendulum
  never terminates and its time limit, 200, is beyond the horizon).

The worker's start is a fixed cost of each evaluation through it. It is timed on its own (below)
and not subtracted from the evaluation rows: it can overlap the evaluation's other work (on a loaded
machine the start timed alone exceeded the worker's whole difference to in-process), so a
difference would mislead.

First (it needs no run), the worker protocol alone, with ``--proto-steps`` vector steps of zero
actions, 1 and 16 environments (tasks cycling over the suite's gravities), in microseconds per
vector step:

- **round trip**: this script speaks the protocol to ``python -m promptdt.worker`` itself (a JSON
  header and float32 payload each way over the pipes, as the Rust side does): one ``step`` request
  answered, the worker stepping the environments inside it;
- **gymnasium direct**: the same environments stepped with the same actions in a Python loop in
  this process;
- **overhead**: round trip minus direct (per repeat, then the median and percentiles): the framing,
  the pipe, the JSON, the worker's checks and copies; the Rust client's side is not in it (this
  script is the client), the evaluation rows above have it;
- **worker start**: spawning the worker, its imports, and the ``init`` request answered (ms).

Ratios (computed by `promptdt bench render`): "Python alone / worker" above 1 means the worker's
evaluation is faster than the user's Python loop; "in-process / worker" is what the process
boundary (start included) costs a whole evaluation.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
GRAVITIES = [6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0]
TRAIN, TEST = [0, 2, 3, 5, 7], [1, 4, 6]


def suite_text(horizon: int) -> str:
    tasks = "".join(f'\n[[tasks]]\nname = "g{int(g)}"\nparams = {{ g = {g} }}\n' for g in GRAVITIES)
    names = lambda ix: json.dumps([f"g{int(GRAVITIES[i])}" for i in ix])  # noqa: E731
    return f"""name = "pendulum_bench"
obs_dim = 3
act_dim = 1
action_bound = 2.0
max_ep_len = {horizon}
rtg_scale = 100
target_return = -200.0
prompt_length = 5
{tasks}
[splits.default]
train = {names(TRAIN)}
test = {names(TEST)}

[environment]
entry = "Pendulum-v1"
python = {json.dumps(sys.executable)}
step_timeout_s = 60
"""


def make_run(root: pathlib.Path, horizon: int, episodes: int):
    """The suite, its data and a Prompt-DT run trained a few steps; returns the run directory."""
    import gymnasium as gym
    import promptdt

    suite = root / "pendulum_bench.toml"
    suite.write_text(suite_text(horizon))
    data = root / "data"
    data.mkdir()
    rng = np.random.default_rng(0)
    for i, g in enumerate(GRAVITIES):
        env = gym.make("Pendulum-v1", g=g)
        for mode, n in [("expert", 4), ("prompt-expert", 2)]:
            trajs = []
            for e in range(n):
                obs, _ = env.reset(seed=100 * i + e)
                o, a, r = [], [], []
                for _ in range(horizon):
                    act = np.clip(np.array([2.0 * np.sign(obs[2]) + rng.normal(0, 0.5)], np.float32), -2, 2)
                    o.append(obs)
                    a.append(act)
                    obs, rew, *_ = env.step(act)
                    r.append(rew)
                trunc = np.zeros(horizon, bool)
                trunc[-1] = True
                trajs.append(promptdt.Trajectory(
                    observations=np.asarray(o, np.float32), actions=np.asarray(a, np.float32),
                    rewards=np.asarray(r, np.float32), terminated=np.zeros(horizon, bool), truncated=trunc))
            ds = promptdt.Dataset(obs_dim=3, act_dim=1, env=str(suite), task=i, mode=mode, trajectories=trajs)
            promptdt.write_dataset(data / f"pendulum_bench-{i}-{mode}.safetensors", ds)
    config = root / "exp.toml"
    config.write_text(f"""[run]
method = "prompt-dt"
seed = 0
threads = 1
device = "cpu"
[env]
name = {json.dumps(str(suite))}
[data]
dir = {json.dumps(str(data))}
[sampler]
k = 20
batch_size_per_task = 4
[train]
iterations = 1
steps_per_iteration = 5
test_eval_interval = 1000  # beyond the run: no evaluation while training
train_eval_interval = 0
save_interval = 1
[eval]
episodes = {episodes}
""")
    promptdt.train(root / "run", config, progress=False)
    return root / "run"


def python_alone(run, gym, episodes: int, horizon: int):
    """The evaluation as a user writes it with `Policy.act` and gymnasium; returns per episode."""
    import promptdt

    policy = promptdt.Policy.load(run, threads=1)
    plan = policy.eval_plan("test", episodes=episodes)
    envs = [gym.make("Pendulum-v1", g=GRAVITIES[t.index]) for t in plan for _ in t.seeds]
    seeds = [s for t in plan for s in t.seeds]
    obs = np.stack([env.reset(seed=s)[0] for env, s in zip(envs, seeds)]).astype(np.float32)
    n = len(envs)
    policy.reset(n)
    policy.set_prompt([t.prompt for t in plan for _ in t.seeds])
    returns = np.zeros(n)
    rew = np.zeros(n, np.float32)
    running = np.ones(n, bool)
    actions = policy.act(obs)
    for t in range(horizon):
        for i, env in enumerate(envs):
            if running[i]:
                o, r, term, trunc, _ = env.step(actions[i])
                obs[i], rew[i] = o, np.float32(r)  # f32 as the worker sends them
                returns[i] += float(rew[i])
                running[i] = not (term or trunc)
        if t + 1 >= horizon or not running.any():
            break
        # An episode that ended early would be acted on in vain from here on (the evaluator drops
        # it from its batch); Pendulum's never do before the horizon, so the batch is the same.
        actions = policy.act(obs, np.where(running, rew, 0.0).astype(np.float32))
    return returns


class Worker:
    """`python -m promptdt.worker` spoken to directly, as the Rust side speaks to it."""

    def __init__(self, n: int):
        self.p = subprocess.Popen([sys.executable, "-m", "promptdt.worker"], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE)
        tasks = [{"index": i % len(GRAVITIES), "name": f"g{i}", "params": {"g": GRAVITIES[i % len(GRAVITIES)]}}
                 for i in range(n)]
        spec = {"entry": "Pendulum-v1", "task_keyword": None, "kwargs": {}, "imports": [], "python": None,
                "step_timeout_s": 60}
        self.call({"op": "init", "protocol": 1, "spec": spec, "tasks": tasks, "obs_dim": 3, "act_dim": 1})

    def call(self, header, payload=None):
        data = b"" if payload is None else np.ascontiguousarray(payload, "<f4").tobytes()
        if payload is not None:
            header = dict(header, payload=len(data) // 4)
        self.p.stdin.write(json.dumps(header).encode() + b"\n" + data)
        self.p.stdin.flush()
        reply = json.loads(self.p.stdout.readline())
        if "error" in reply:
            raise RuntimeError(f"the worker answered {reply}")
        return reply, np.frombuffer(self.p.stdout.read(4 * reply.get("payload", 0)), "<f4")

    def close(self):
        self.p.stdin.close()
        self.p.wait()


def protocol(gym, n: int, steps: int):
    """(round trip us, direct us) per vector step of n environments, and the worker's start ms."""
    t0 = time.perf_counter()
    w = Worker(n)
    start_ms = 1e3 * (time.perf_counter() - t0)
    w.call({"op": "reset", "seeds": list(range(n))})
    acts = np.zeros((n, 1), np.float32)
    slots = list(range(n))
    t0 = time.perf_counter()
    for _ in range(steps):
        w.call({"op": "step", "slots": slots}, acts)
    trip = (time.perf_counter() - t0) / steps * 1e6
    w.close()
    envs = [gym.make("Pendulum-v1", g=GRAVITIES[i % len(GRAVITIES)]) for i in range(n)]
    for i, e in enumerate(envs):
        e.reset(seed=i)
    t0 = time.perf_counter()
    for _ in range(steps):
        for i, e in enumerate(envs):
            e.step(acts[i])
    direct = (time.perf_counter() - t0) / steps * 1e6
    return trip, direct, start_ms


def sig(x: float) -> float:
    """4 significant digits, as the Rust records keep them (`record::significant`)."""
    return float(f"{x:.4g}")


def spread(xs):
    return {"median": sig(float(np.median(xs))), "p10": sig(float(np.percentile(xs, 10))),
            "p90": sig(float(np.percentile(xs, 90)))}


def machine():
    model = next((line.split(":", 1)[1].strip() for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), os.uname().machine)
    return {"cpu": f"{model}, {len(os.sched_getaffinity(0))} cores"}


def commit():
    try:
        out = subprocess.run(["git", "rev-parse", "--short=7", "HEAD"], cwd=ROOT, capture_output=True, text=True)
        return out.stdout.strip() or None if out.returncode == 0 else None
    except OSError:
        return None


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json-out", help="write the benchmark record here (benchmarks/16-worker.json)")
    ap.add_argument("--horizon", type=int, default=100, help="the suite's max_ep_len (steps per episode)")
    ap.add_argument("--episodes", type=int, nargs="+", default=[1, 5], help="episodes per held-out task, one row each")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--proto-steps", type=int, default=2000)
    ap.add_argument("--conditions", default="", help="what else ran on the machine (goes into the record)")
    args = ap.parse_args()
    if not 1 <= args.horizon <= 200:
        # Pendulum-v1's own time limit is 200 steps: beyond it episodes would end before the
        # horizon, and the rows' vector steps (every episode at the horizon) would be wrong.
        ap.error(f"--horizon {args.horizon}: must be 1 to 200 (Pendulum-v1's time limit)")
    import promptdt

    promptdt.set_num_threads(1)
    load_before = os.getloadavg()[0]
    started = time.perf_counter()
    eval_rows, proto_rows, start_ms = [], [], []
    import gymnasium as gym

    for n in (1, 16):
        trips, directs = [], []
        for _ in range(args.repeats):
            trip, direct, ms = protocol(gym, n, args.proto_steps)
            trips.append(trip)
            directs.append(direct)
            start_ms.append(ms)
        overhead = [a - b for a, b in zip(trips, directs)]
        proto_rows.append({"case": f"{n} env{'s' if n > 1 else ''}",
                           "values": [spread(trips), spread(directs), spread(overhead)]})
        print(f"{n:>3} envs: round trip {np.median(trips):.1f} us, direct {np.median(directs):.1f} us, "
              f"overhead {np.median(overhead):.1f} us per vector step", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        run = make_run(pathlib.Path(tmp), args.horizon, max(args.episodes))

        def factory(task):
            return gym.make("Pendulum-v1", **task["params"])

        for episodes in args.episodes:
            modes = {
                "worker": lambda: promptdt.evaluate(run, episodes=episodes, progress=False),
                "in-process": lambda: promptdt.evaluate(run, episodes=episodes, progress=False, env=factory),
                "alone": lambda: python_alone(run, gym, episodes, args.horizon),
            }
            results = {name: f() for name, f in modes.items()}  # warm-up, and the returns compared
            worker = [r for t in results["worker"]["tasks"] for r in t["returns"]]
            inproc = [r for t in results["in-process"]["tasks"] for r in t["returns"]]
            alone = results["alone"].tolist()
            if not (worker == inproc == alone):
                sys.exit(f"the returns differ ({episodes} episodes per task):\n worker     {worker}\n"
                         f" in-process {inproc}\n Python     {alone}")
            times = {name: [] for name in modes}
            for _ in range(args.repeats):
                for name, f in modes.items():  # interleaved, so that load drifts reach all three
                    t0 = time.perf_counter()
                    f()
                    times[name].append(1e3 * (time.perf_counter() - t0))
            steps = args.horizon
            n = len(worker)
            case = f"{len(TEST)} tasks x {episodes} episode{'s' if episodes > 1 else ''} ({n} envs), {steps} steps"
            eval_rows.append({"case": case,
                              "values": [spread(times["worker"]), spread(times["in-process"]),
                                         spread(times["alone"]), steps]})
            print(f"{n:>3} envs: worker {np.median(times['worker']):.1f} ms, in-process "
                  f"{np.median(times['in-process']):.1f} ms, Python alone {np.median(times['alone']):.1f} ms; "
                  f"returns equal ({n} episodes)", flush=True)
    load_after = os.getloadavg()[0]
    wall = time.perf_counter() - started
    print(f"worker start {np.median(start_ms):.0f} ms; {wall:.0f} s in all; load {load_before:.1f} -> {load_after:.1f}")
    if not args.json_out:
        return
    conditions = f"1-minute load average {load_before:.1f} before, {load_after:.1f} after"
    if args.conditions:
        conditions = f"{args.conditions}; {conditions}"
    record = {
        "title": "The environment worker: a suite's evaluation through the worker, in-process, and in Python alone",
        "what": (
            f"`scripts/bench/bench_worker.py` (its docstring defines each column), one process tree: a Pendulum-v1 "
            f"suite with gravity as the task, trained a few steps (K = 20, one thread), evaluated on its "
            f"{len(TEST)} held-out tasks by `promptdt.evaluate(run)` (Rust driving `python -m promptdt.worker`), by "
            f"`promptdt.evaluate(run, env=factory)` (the same requests answered in-process) and by a gymnasium loop "
            f"with `Policy.act` (same prompts, target and reset seeds; returns checked equal bit for bit); ms per "
            f"whole evaluation, worker start and run loading included, median (p10-p90) of {args.repeats}. Then the "
            f"worker protocol alone: one `step` request's round trip against stepping the same gymnasium "
            f"environments directly, microseconds per vector step, {args.proto_steps} steps, {args.repeats} repeats; "
            f"Python {sys.version.split()[0]}, gymnasium {gym.__version__}."),
        "commands": ["bash scripts/install_python.sh",
                     ".venv-promptdt/bin/python scripts/bench/bench_worker.py --json-out benchmarks/16-worker.json"],
        "machine": machine(),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
        **({"commit": c} if (c := commit()) else {}),
        "conditions": conditions,
        "tables": [
            {"case": "evaluation", "columns": ["worker process ms", "in-process (`env=factory`) ms",
                                               "Python alone ms", "vector steps"],
             "ratios": [{"label": "Python alone / worker", "num": 2, "den": 0},
                        {"label": "Python alone / in-process", "num": 2, "den": 1},
                        {"label": "in-process / worker", "num": 1, "den": 0}],
             "rows": eval_rows},
            {"case": "worker protocol, per vector step",
             "columns": ["round trip us", "gymnasium direct us", "overhead us"],
             "ratios": [{"label": "direct / round trip", "num": 1, "den": 0}],
             "rows": proto_rows},
            {"case": "worker start", "columns": ["spawn, imports, `init` answered, ms"],
             "rows": [{"case": f"{len(start_ms)} starts", "values": [spread(start_ms)]}]},
        ],
    }
    out = pathlib.Path(args.json_out)
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=2) + "\n")
    tmp.replace(out)  # atomic: a failed run leaves the old record
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
