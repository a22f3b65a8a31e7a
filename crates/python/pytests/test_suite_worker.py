"""Issue 53: a user's task suite with a real gymnasium environment, end to end through the front
ends with no Rust written: gymnasium's ``Pendulum-v1`` whose gravity ``g`` is the task, declared in
a suite file; its data written with ``promptdt.write_dataset``; Prompt-DT trained on it (its
periodic evaluations played in a worker process that runs this interpreter); then the same run
evaluated through the worker (``promptdt.evaluate(run)``, what ``promptdt eval`` does) and in this
process from a Python factory (``env=factory``): the returns are equal bit for bit."""
import json
import sys

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

import promptdt  # noqa: E402

GRAVITIES = [8.0, 9.0, 10.0, 11.0]

SUITE = f"""
name = "pendulum_g"
obs_dim = 3
act_dim = 1
action_bound = 2.0
max_ep_len = 20
rtg_scale = 100
target_return = 0.0
prompt_length = 5
{"".join(f'''
[[tasks]]
name = "g{int(g)}"
params = {{ g = {g} }}
''' for g in GRAVITIES)}
[splits.default]
train = ["g8", "g9", "g10"]
test = ["g11"]

[environment]
entry = "Pendulum-v1"
python = {json.dumps(sys.executable)}
step_timeout_s = 30
"""


def episode(env, rng, seed):
    """One 20-step episode of a noisy swing policy (the data need not be good, only real)."""
    obs, _ = env.reset(seed=seed)
    o, a, r = [], [], []
    for _ in range(20):
        act = np.clip(np.array([2.0 * np.sign(obs[2]) + rng.normal(0, 0.5)], np.float32), -2, 2)
        o.append(obs)
        a.append(act)
        obs, rew, term, trunc, _ = env.step(act)
        r.append(rew)
    truncated = np.zeros(20, bool)
    truncated[-1] = True
    return promptdt.Trajectory(
        observations=np.asarray(o, np.float32), actions=np.asarray(a, np.float32),
        rewards=np.asarray(r, np.float32), terminated=np.zeros(20, bool), truncated=truncated)


def pendulum(task):
    """The factory of the suite's environments in this process: its ``[environment]``'s."""
    return gym.make("Pendulum-v1", **task["params"])


def eval_returns(run):
    """Each line of the run's eval.jsonl as (iteration, task, mean return, its std)."""
    lines = [json.loads(x) for x in (run / "eval.jsonl").read_text().splitlines()]
    return [(x["iteration"], x["task"], x["return_mean"], x["return_std"]) for x in lines]


@pytest.fixture(scope="module")
def suite_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("suite")
    suite = root / "pendulum_g.toml"
    suite.write_text(SUITE)
    data = root / "data"
    data.mkdir()
    rng = np.random.default_rng(0)
    for i, g in enumerate(GRAVITIES):
        env = gym.make("Pendulum-v1", g=g)
        for mode, n in [("expert", 6), ("prompt-expert", 2)]:
            ds = promptdt.Dataset(obs_dim=3, act_dim=1, env=str(suite), task=i, mode=mode,
                                  trajectories=[episode(env, rng, 100 * i + e) for e in range(n)])
            promptdt.write_dataset(data / f"pendulum_g-{i}-{mode}.safetensors", ds)
    config = root / "exp.toml"
    config.write_text(f"""
[run]
method = "prompt-dt"
seed = 0
threads = 1
device = "cpu"
[env]
name = {json.dumps(str(suite))}
[data]
dir = {json.dumps(str(data))}
[sampler]
k = 5
batch_size_per_task = 4
[train]
iterations = 2
steps_per_iteration = 5
test_eval_interval = 1
train_eval_interval = 0
save_interval = 1
[eval]
episodes = 2
""")
    out = root / "run"
    summary = promptdt.train(out, config, progress=False)
    assert summary["finished"] and summary["iterations_done"] == 2
    # The periodic evaluations were played in the worker: a return per test task.
    assert summary["last_test_mean"] is not None
    return out


def test_a_suite_run_evaluates_the_same_through_the_worker_and_in_process(suite_run):
    through_worker = promptdt.evaluate(suite_run, progress=False)
    made = []

    def factory(task):
        made.append(task)
        return gym.make("Pendulum-v1", **task["params"])

    in_process = promptdt.evaluate(suite_run, progress=False, env=factory)
    assert in_process == through_worker
    assert [t["returns"] for t in in_process["tasks"]] == [t["returns"] for t in through_worker["tasks"]]
    # The held-out task, as the suite names it, twice (eval.episodes = 2).
    assert made == [{"index": 3, "name": "g11", "params": {"g": 11.0}}] * 2
    # Pendulum's rewards are at most 0 and its episodes here 20 steps long.
    assert all(r <= 0 for t in in_process["tasks"] for r in t["returns"])


def test_train_with_a_factory_evaluates_as_the_worker_does(suite_run, tmp_path):
    """``train(..., env=factory)``: the periodic evaluations played in this process give the
    returns the worker gave the same run (same seed, data, suite), line for line; on the same
    suite without ``[environment]`` too, which is then evaluated in the factory's environments
    instead of offline."""
    root = suite_run.parent
    config = root / "exp.toml"
    out = tmp_path / "run"
    summary = promptdt.train(out, config, progress=False, env=pendulum)
    assert summary["finished"]
    assert eval_returns(out) == eval_returns(suite_run)

    bare = tmp_path / "pendulum_g.toml"
    bare.write_text(SUITE.split("[environment]")[0])
    bare_config = tmp_path / "bare.toml"
    bare_config.write_text(config.read_text().replace(json.dumps(str(root / "pendulum_g.toml")),
                                                      json.dumps(str(bare))))
    offline = promptdt.train(tmp_path / "offline", bare_config, progress=False)
    logged = tmp_path / "offline" / "eval.jsonl"
    assert not logged.exists() or not logged.read_text()
    assert (tmp_path / "offline" / "offline_eval.jsonl").read_text()
    assert offline["last_test_mean"] is None

    played = tmp_path / "played"
    promptdt.train(played, bare_config, progress=False, env=pendulum, iterations=1)
    # A run evaluated in a factory's environments resumes only with environments again ...
    with pytest.raises(promptdt.InvalidInputError, match=r"played.*eval\.jsonl.*none are given now.*env=factory"):
        promptdt.train(played, resume=True, iterations=2, progress=False)
    summary = promptdt.train(played, resume=True, iterations=2, progress=False, env=pendulum)
    assert summary["finished"] and summary["last_test_mean"] is not None
    assert eval_returns(played) == eval_returns(suite_run)
    assert not (played / "offline_eval.jsonl").exists()
    # ... and one evaluated offline never switches to returns.
    with pytest.raises(promptdt.InvalidInputError, match=r"offline.*offline_eval\.jsonl.*environments are given now"):
        promptdt.train(tmp_path / "offline", resume=True, iterations=3, progress=False, env=pendulum)
