"""Issue 53 item 4: ``promptdt.collect(suite, out, policy=...)`` collects a task suite's expert,
medium and random datasets in its environment (here gymnasium's ``Pendulum-v1`` with gravity ``g``
as the task) from a Python policy, in this process. The same bytes whatever the batching and
whether the environments come from the suite's ``[environment]`` or a factory; a policy or
environment that misbehaves is an ``InvalidInputError`` naming the task and step, with no card.
(The CLI's ``promptdt collect --policy`` writing the same bytes is
``crates/cli/tests/it/collect_suite.rs``.)"""
import json
import sys

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

import promptdt  # noqa: E402

SUITE = f"""
name = "pend_py"
obs_dim = 3
act_dim = 1
action_bound = 2.0
max_ep_len = 12
rtg_scale = 100
target_return = 0.0
prompt_length = 4

[[tasks]]
name = "light"
params = {{ g = 5.0 }}

[[tasks]]
name = "heavy"
params = {{ g = 12.0 }}

[splits.default]
train = ["light"]
test = ["heavy"]

[environment]
entry = "Pendulum-v1"
python = {json.dumps(sys.executable)}
"""


def swing(obs, task):
    return np.array([np.clip(2.0 * np.sign(obs[2]) * 10.0 / task["params"]["g"], -2.0, 2.0)])


def make(task):
    return gym.make("Pendulum-v1", **task["params"])


@pytest.fixture()
def suite(tmp_path):
    path = tmp_path / "pend.toml"
    path.write_text(SUITE)
    return path


def files(d, card=True):
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())
            if card or p.suffix == ".safetensors"}


def test_collect_from_a_policy_is_a_function_of_the_seed(suite, tmp_path):
    kw = dict(episodes=3, prompt_episodes=2, seed=5, progress=False)
    n = promptdt.collect(suite, tmp_path / "a", policy=swing, envs_per_task=3, **kw)
    assert n == 12  # 2 tasks x 3 levels x (dataset, prompt set)
    promptdt.collect(suite, tmp_path / "b", policy=swing, envs_per_task=1, **kw)
    promptdt.collect(suite, tmp_path / "c", policy=swing, factory=make, **kw)
    assert files(tmp_path / "a") == files(tmp_path / "b")
    assert files(tmp_path / "a", card=False) == files(tmp_path / "c", card=False)
    expert = promptdt.load_dataset(tmp_path / "a" / "pend_py-1-expert.safetensors")
    assert expert.env == "pend_py" and len(expert) == 3
    assert all(len(t) == 12 and t.truncated[-1] for t in expert.trajectories)
    # The expert is the policy (no noise by default), float32 and clipped into the bounds.
    want = np.float32(min(2.0, 20.0 / 12.0))
    assert all(np.all(np.abs(t.actions) == want) for t in expert.trajectories)
    card = json.loads((tmp_path / "a" / "dataset.json").read_text())
    assert card["generator"]["expert_policy"].endswith(":swing")
    assert card["generator"]["prompt_rule"] == "best:2"
    # A second policy makes the medium level.
    promptdt.collect(suite, tmp_path / "m", policy=swing, medium_policy=lambda o, t: [0.5],
                     modes=["medium"], tasks=[0], **kw)
    medium = promptdt.load_dataset(tmp_path / "m" / "pend_py-0-medium.safetensors")
    assert all(np.all(t.actions == 0.5) for t in medium.trajectories)


@pytest.mark.parametrize("policy, words", [
    (lambda o, t: [float("nan")], ["light (task 0), step 1", "non-finite action"]),
    (lambda o, t: [0.0, 1.0], ["step 1", "shape (2,)", "act_dim = 1"]),
    (lambda o, t: 1 / 0 if t["index"] == 1 else [0.0], ["heavy (task 1)", "ZeroDivisionError"]),
])
def test_a_misbehaving_policy_is_named_and_leaves_no_card(suite, tmp_path, policy, words):
    with pytest.raises(promptdt.InvalidInputError) as e:
        promptdt.collect(suite, tmp_path / "out", policy=policy, episodes=2, progress=False)
    assert all(w in str(e.value) for w in words), str(e.value)
    assert not (tmp_path / "out" / "dataset.json").exists()


def test_bad_arguments_are_refused_before_anything_runs(suite, tmp_path):
    with pytest.raises(promptdt.InvalidInputError, match="needs policy="):
        promptdt.collect(suite, tmp_path / "x")
    with pytest.raises(promptdt.ArgumentTypeError, match="policy: expected a callable"):
        promptdt.collect(suite, tmp_path / "x", policy=3)
    with pytest.raises(promptdt.InvalidInputError, match="for a task suite"):
        promptdt.collect("point_robot", tmp_path / "x", policy=swing)

    def raising(task):
        raise ValueError("no such planet")
    with pytest.raises(promptdt.InvalidInputError, match="no such planet"):
        promptdt.collect(suite, tmp_path / "x", policy=swing, factory=raising, progress=False)
    assert not (tmp_path / "x" / "dataset.json").exists()
