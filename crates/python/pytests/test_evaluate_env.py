"""Issue 53 item 3(a): ``promptdt.evaluate(run, env=factory)``, the episodes played in
environments a Python factory makes in this process. The factory here returns promptdt's own
gymnasium environment of the run's family, so the in-process path (Rust's checks, requests
answered by ``promptdt.worker.Session(factory)``) is checked against the Rust path on the same
environment: the returns are equal bit for bit. Bad factories are refused by name."""
import json

import pytest

gym = pytest.importorskip("gymnasium")

import promptdt  # noqa: E402


def test_a_factory_of_the_familys_own_env_gives_the_rust_returns_bit_for_bit(point_run):
    reference = promptdt.evaluate(point_run, episodes=3, progress=False)
    written = (point_run / "eval_final.json").read_bytes()
    made, seen = [], []

    def factory(task):
        made.append(task)
        return gym.make("promptdt/PointRobot-v0", task=task["index"])

    got = promptdt.evaluate(point_run, episodes=3, progress=seen.append, env=factory)
    # Same dict, floats compared exactly: each episode's return, mean, std, length and success.
    assert got == reference
    assert [t["returns"] for t in got["tasks"]] == [t["returns"] for t in reference["tasks"]]
    # One environment per episode, each told its task as the family knows it.
    tasks = {t["task_index"] for t in reference["tasks"]}
    assert len(made) == 3 * len(tasks) and {t["index"] for t in made} == tasks
    for t in made:
        assert t["name"] == f"point_robot-{t['index']}"
        assert t["params"] == promptdt.task_params("point_robot", t["index"])
    # Progress as without env=; the run's file is the run's own evaluation, not rewritten.
    assert seen and seen[-1]["done"] == seen[-1]["total"] == 3 * len(tasks)
    assert (point_run / "eval_final.json").read_bytes() == written


class Raising:
    def __call__(self, task):
        raise ValueError(f"no goal for {task['name']}")


@pytest.mark.parametrize("factory, message", [
    (Raising(), r"point_robot-\d+ \(task \d+\).*making its environment raised ValueError: no goal for point_robot-\d+"),
    (lambda task: gym.make("Pendulum-v1"), r"point_robot-\d+ \(task \d+\).*observation space has shape \(3,\) \(3 values\), but the suite declares 2"),
])
def test_bad_factories_are_named_promptdt_errors(point_run, factory, message):
    before = (point_run / "eval_final.json").read_bytes()
    with pytest.raises(promptdt.InvalidInputError, match=message):
        promptdt.evaluate(point_run, episodes=1, progress=False, env=factory)
    assert (point_run / "eval_final.json").read_bytes() == before


def test_env_must_be_callable(point_run):
    with pytest.raises(promptdt.ArgumentTypeError, match=r"env: expected a callable factory"):
        promptdt.evaluate(point_run, env="promptdt/PointRobot-v0")
