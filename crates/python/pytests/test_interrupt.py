"""Ctrl-C stops promptdt.train, promptdt.evaluate and promptdt.collect within 5 s with
KeyboardInterrupt, the run resumes and finishes afterwards, and the three calls report progress (a
line on stderr, a callback, or nothing): evaluate's and a scripted collection's per episode."""
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

import promptdt

REPO_CONFIG = "configs/point_robot/demo.toml"


def _long_config(repo, root, iterations):
    """The demo's Prompt-DT with many iterations, a resume point after each (so the interrupted run
    keeps its work) and one libtorch thread."""
    text = (repo / REPO_CONFIG).read_text()
    text = text.replace("iterations = 40", f"iterations = {iterations}")
    text = text.replace("test_eval_interval = 5", "test_eval_interval = 1000")
    text = text.replace("episodes = 20", "episodes = 2")
    text = text.replace("save_interval = 20", "save_interval = 1000\nresume_interval = 1")
    text = text.replace("[run]\n", "[run]\nthreads = 1\ndevice = \"cpu\"\n")
    config = root / "long.toml"
    config.write_text(text)
    return config


def _interrupt(code, started, cwd, timeout=120):
    """Runs `code` in a new Python, waits until `started(stderr so far)` holds, sends SIGINT and
    returns (seconds from SIGINT to exit, return code, stderr)."""
    err_path = cwd / "stderr.txt"
    with open(err_path, "w") as err:
        proc = subprocess.Popen([sys.executable, "-c", code], cwd=cwd, stderr=err,
                                stdout=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + timeout
        while not started(err_path.read_text()):
            assert proc.poll() is None, f"ended before it could be interrupted: {err_path.read_text()}"
            assert time.monotonic() < deadline, "never started"
            time.sleep(0.1)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pytest.fail("still running 30 s after SIGINT")
        return time.monotonic() - t0, proc.returncode, err_path.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _metrics_lines(run):
    path = run / "metrics.jsonl"
    return len(path.read_text().splitlines()) if path.exists() else 0


def test_ctrl_c_stops_train_within_5s_and_the_run_resumes(repo, point_data, tmp_path):
    total = 100000  # hours of training: only an interruption ends it
    config = _long_config(repo, tmp_path, total)
    out = tmp_path / "run"
    code = (f"import promptdt; promptdt.train({str(out)!r}, {str(config)!r}, "
            f"data={str(point_data)!r})")
    elapsed, rc, err = _interrupt(code, lambda _: _metrics_lines(out) >= 3, tmp_path)
    print(f"train: SIGINT -> exit in {elapsed:.2f} s")
    assert elapsed < 5.0, f"took {elapsed:.1f} s to stop"
    assert rc != 0 and "KeyboardInterrupt" in err, err[-2000:]
    # The default progress line went to stderr: iteration, loss and the time left.
    assert f"/{total}" in err and "loss" in err and "ETA" in err, err[-2000:]
    latest = json.loads((out / "checkpoints/latest.json").read_text())
    done = latest["iteration"]
    assert done >= 2
    # The run goes on from its last resume point and finishes (extended by 2 iterations only).
    seen = []
    summary = promptdt.train(out, resume=True, iterations=done + 2, progress=seen.append)
    assert summary["finished"] and summary["iterations_done"] == done + 2
    assert [p["iteration"] for p in seen] == [done + 1, done + 2]
    assert all(p["iterations"] == done + 2 and p["loss"] > 0 for p in seen)
    assert _metrics_lines(out) == done + 2


def test_train_progress_can_be_turned_off(repo, point_data, tmp_path):
    config = _long_config(repo, tmp_path, 2)
    code = (f"import promptdt; promptdt.train({str(tmp_path / 'r')!r}, {str(config)!r}, "
            f"data={str(point_data)!r}, progress=False)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "ETA" not in done.stderr and "loss" not in done.stderr


def test_ctrl_c_stops_collect_within_5s(tmp_path):
    out = tmp_path / "reach"
    code = (f"import promptdt; promptdt.collect('metaworld_reach', {str(out)!r}, episodes=200)")
    files = lambda _: out.is_dir() and any(p.suffix == ".safetensors" for p in out.iterdir())
    elapsed, rc, err = _interrupt(code, files, tmp_path)
    print(f"collect: SIGINT -> exit in {elapsed:.2f} s")
    assert elapsed < 5.0, f"took {elapsed:.1f} s to stop"
    assert rc != 0 and "KeyboardInterrupt" in err, err[-2000:]
    assert not (out / "dataset.json").exists()
    # Every file written before the stop is whole, and collecting again finishes.
    for p in out.glob("*.safetensors"):
        assert len(promptdt.load_dataset(p)) > 0
    seen = []
    n = promptdt.collect("metaworld_reach", out, episodes=2, prompt_episodes=1, progress=seen.append)
    assert n == len(list(out.glob("*.safetensors"))) and (out / "dataset.json").exists()
    assert seen and seen[-1]["done"] == seen[-1]["total"]


def _test_tasks():
    return len(promptdt.families()["point_robot"]["splits"]["default"][1])


@pytest.fixture
def small_batch_run(point_run, tmp_path):
    """The tiny run with batches of 16 episodes (`eval.max_batch`): a long evaluation of short
    steps. The default batch (4096 episodes) makes one step a forward of 4096 histories, seconds
    on one thread, and Ctrl-C is seen between steps."""
    run = tmp_path / "run"
    shutil.copytree(point_run, run)
    config = run / "config.toml"
    text = config.read_text()
    assert "max_batch = 4096" in text
    config.write_text(text.replace("max_batch = 4096", "max_batch = 16"))
    return run


def test_ctrl_c_stops_evaluate_within_5s_and_writes_nothing(small_batch_run, tmp_path):
    """Issue 56: evaluate ignored Ctrl-C (60 s on) and showed no progress. 10,000 episodes per
    task (the most eval.episodes takes) are well over 5 s; SIGINT once the default progress line
    shows episodes done."""
    final = small_batch_run / "eval_final.json"
    before = final.read_bytes() if final.exists() else None
    code = f"import promptdt; promptdt.evaluate({str(small_batch_run)!r}, episodes=10000)"
    line = f"/{10000 * _test_tasks()} episodes"
    elapsed, rc, err = _interrupt(code, lambda e: line in e, tmp_path)
    print(f"evaluate: SIGINT -> exit in {elapsed:.2f} s")
    assert elapsed < 5.0, f"took {elapsed:.1f} s to stop"
    assert rc != 0 and "KeyboardInterrupt" in err, err[-2000:]
    # The default line: episodes done of all planned, and the time left.
    assert "ETA" in err and f"evaluate {10000 * _test_tasks()}{line}" not in err, err[-2000:]
    assert (final.read_bytes() if final.exists() else None) == before


def test_evaluate_reports_progress_and_its_callable_can_stop_it(small_batch_run):
    seen = []
    result = promptdt.evaluate(small_batch_run, episodes=7, progress=seen.append)
    total = 7 * _test_tasks()
    assert seen and all(p["unit"] == "episodes" and p["total"] == total for p in seen), seen
    assert seen[-1]["done"] == total and len(result["tasks"]) == _test_tasks()
    assert [p["done"] for p in seen] == sorted(p["done"] for p in seen)

    class Enough(Exception):
        pass

    def stop(p):
        raise Enough(p["done"])

    with pytest.raises(Enough):
        promptdt.evaluate(small_batch_run, episodes=10000, progress=stop)


def test_scripted_collect_reports_episodes_before_a_task_is_written(tmp_path):
    """Issue 56: a scripted collection reported once per (task, mode), so Meta-World reach's first
    report came after 200 episodes (over 150 s on 2 cores). Now episodes are counted as they are
    played: the first report comes before any (task, mode) has its 40 episodes."""
    seen = []

    class Enough(Exception):
        pass

    def first(p):
        seen.append(p)
        raise Enough()

    out = tmp_path / "reach"
    with pytest.raises(Enough):
        promptdt.collect("metaworld_reach", out, episodes=40, prompt_episodes=1, progress=first)
    (p,) = seen
    assert p["unit"] == "episodes" and p["total"] == 20 * 3 * (40 + 1), p
    assert 1 <= p["done"] < 40, p
    assert not [f for f in out.glob("*.safetensors") if "-prompt-" not in f.name]
