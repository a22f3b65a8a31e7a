"""Issue 53 item 3(a): ``promptdt.evaluate(run, env=factory)``, the episodes played in
environments a Python factory makes in this process. The factory here returns promptdt's own
gymnasium environment of the run's family, so the in-process path (Rust's checks, requests
answered by ``promptdt.worker.Session(factory)``) is checked against the Rust path on the same
environment: the returns are equal bit for bit. Bad factories are refused by name."""
import json

import pytest

gym = pytest.importorskip("gymnasium")

import promptdt  # noqa: E402


def final(run):
    """The run's eval_final.json, None before any evaluation wrote it."""
    path = run / "eval_final.json"
    return path.read_bytes() if path.exists() else None


def test_a_factory_of_the_familys_own_env_gives_the_rust_returns_bit_for_bit(point_run):
    reference = promptdt.evaluate(point_run, episodes=3, progress=False)
    written = final(point_run)
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
    assert final(point_run) == written


class Raising:
    def __call__(self, task):
        raise ValueError(f"no goal for {task['name']}")


@pytest.mark.parametrize("factory, message", [
    (Raising(), r"point_robot-\d+ \(task \d+\).*making its environment raised ValueError: no goal for point_robot-\d+"),
    (lambda task: gym.make("Pendulum-v1"), r"point_robot-\d+ \(task \d+\).*observation space has shape \(3,\) \(3 values\), but the suite declares 2"),
])
def test_bad_factories_are_named_promptdt_errors(point_run, factory, message):
    before = final(point_run)
    with pytest.raises(promptdt.InvalidInputError, match=message):
        promptdt.evaluate(point_run, episodes=1, progress=False, env=factory)
    assert final(point_run) == before


def test_env_must_be_callable(point_run):
    with pytest.raises(promptdt.ArgumentTypeError, match=r"env: expected a callable factory"):
        promptdt.evaluate(point_run, env="promptdt/PointRobot-v0")


def test_ctrl_c_stops_an_evaluation_in_the_factorys_envs(point_run, tmp_path):
    """Ctrl-C as without env=: the episodes stop at their next step within 5 s, KeyboardInterrupt
    is raised and nothing is written. Batches of 16 episodes (`eval.max_batch`), 1,000 per task:
    well over 5 s of episodes stepped in Python."""
    import shutil
    import signal
    import subprocess
    import sys
    import time

    run = tmp_path / "run"
    shutil.copytree(point_run, run)
    config = run / "config.toml"
    config.write_text(config.read_text().replace("max_batch = 4096", "max_batch = 16"))
    before = final(run)
    code = ("import gymnasium, promptdt; promptdt.evaluate(%r, episodes=1000, env=lambda t: "
            "gymnasium.make('promptdt/PointRobot-v0', task=t['index']))" % str(run))
    err_path = tmp_path / "stderr.txt"
    with open(err_path, "w") as err:
        proc = subprocess.Popen([sys.executable, "-c", code], stderr=err, stdout=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        # The progress line once episodes have ended: the environments are made and stepping.
        while "episodes" not in err_path.read_text():
            assert proc.poll() is None, err_path.read_text()[-2000:]
            assert time.monotonic() < deadline, "never started"
            time.sleep(0.1)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
        elapsed = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = err_path.read_text()
    assert elapsed < 5.0, f"took {elapsed:.1f} s to stop"
    assert proc.returncode != 0 and "KeyboardInterrupt" in text, text[-2000:]
    assert final(run) == before
