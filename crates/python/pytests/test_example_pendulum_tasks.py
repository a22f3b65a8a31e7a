"""Issue 53: the small worked example (examples/pendulum_tasks) end to end, by the README's own
commands: a user's gymnasium task family (Pendulum-v1, the pole mass as the task) defined in a few
lines of Python, its data written with ``promptdt.write_dataset``, Prompt-DT trained through the
CLI (evaluations in the user's environments through the worker), evaluated from the CLI and from
Python with equal returns, reported, and served for one episode; no front end names the suite
(``crates/testkit/tests/it/user_suites.rs`` checks that no Rust source does)."""
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest

pytest.importorskip("gymnasium")

EXAMPLE = "examples/pendulum_tasks"


def readme_block(repo, doc="README.md"):
    text = (repo / doc).read_text()
    m = re.search(r"<!-- tasks-example[^>]*-->\n```sh\n(.*?)```", text, re.S)
    assert m, f"{doc} has no tasks-example block"
    return m.group(1)


@pytest.fixture(scope="module")
def example(repo, tmp_path_factory):
    """The README's block run as written, in a copy of the example (so nothing is written into
    the checkout); returns the example's directory and what the block printed."""
    exe = promptdt_exe(repo)
    work = tmp_path_factory.mktemp("checkout")
    # Only the example's committed files: a run or data of a user's own try are not copied.
    shutil.copytree(repo / EXAMPLE, work / EXAMPLE, ignore=shutil.ignore_patterns("data", "runs", "__pycache__"))
    # `python` and `python3` (the worker's default interpreter) are this one, with promptdt.
    path = os.pathsep.join([str(exe.parent), os.path.dirname(sys.executable), os.environ["PATH"]])
    env = dict(os.environ, PATH=path, PYTHONDONTWRITEBYTECODE="1")
    env.pop("PROMPTDT_PYTHON", None)
    out = subprocess.run(["bash", "-euo", "pipefail", "-c", readme_block(repo)], cwd=work, env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, f"stdout:\n{out.stdout}\nstderr:\n{out.stderr}"
    return work / EXAMPLE, out.stdout


def promptdt_exe(repo):
    exe = pathlib.Path(os.environ.get("PROMPTDT_BIN") or repo / "target" / "release" / "promptdt")
    if not exe.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"{exe} is missing: CI builds it in `make test` before the Python tests")
        pytest.skip("no promptdt binary (cargo build --release -p promptdt, or PROMPTDT_BIN)")
    return exe


def test_readme_block_is_the_whole_pipeline(repo):
    block = readme_block(repo)
    # Copy-pasteable: commands only, each a front end a user types (no test scaffolding).
    commands = [line.split("#")[0].split() for line in block.splitlines() if line.strip()]
    assert [c[:2] for c in commands] == [
        ["cd", EXAMPLE], ["python", "collect.py"], ["promptdt", "train"], ["promptdt", "eval"],
        ["python", "evaluate.py"], ["promptdt", "report"], ["python", "serve_episode.py"]]
    # docs/your-own-tasks.md shows the same lines: the copy there cannot drift either.
    assert readme_block(repo, "docs/your-own-tasks.md") == block


def test_every_front_end_takes_the_suite(example):
    here, stdout = example
    run = here / "runs/prompt-dt"
    # train: the suite's name recorded, its copy kept, evaluations played (through the worker).
    info = json.loads((run / "run.json").read_text())
    assert info["env"] == "pendulum_mass", info
    assert (run / "suite.toml").read_text() == (here / "suite.toml").read_text()
    evals = [json.loads(line) for line in (run / "eval.jsonl").read_text().splitlines()]
    # Every 10 iterations from the first, and at the last, both held-out tasks (6 and 7).
    assert [(e["iteration"], e["task_index"]) for e in evals] == [
        (i, t) for i in (1, 11, 21, 30) for t in (6, 7)], evals
    # eval: the two held-out masses, 4 episodes each, 100 steps (the suite's horizon).
    final = json.loads((run / "eval_final.json").read_text())
    assert [t["task_index"] for t in final["tasks"]] == [6, 7]
    assert all(t["episodes"] == 4 and t["length_mean"] == 100.0 for t in final["tasks"])
    # Python: evaluate.py asserted equal returns, episode by episode.
    assert "equal to promptdt eval's, episode by episode" in stdout
    # report: the suite's table and curves.
    table = (here / "runs/report/table.md").read_text()
    assert "pendulum_mass" in table and "prompt-dt" in table, table
    assert (here / "runs/report/curves_pendulum_mass.png").is_file()
    # serve: one whole episode of the first held-out task in the user's environment.
    m = re.search(r"served prompt-dt \(iteration 30\): one episode of task 6 \{'mass': 1.1\}, "
                  r"100 steps, return (-?[0-9.]+)", stdout)
    assert m, stdout


def test_reproduce_runs_a_users_manifest_on_the_suite_to_its_report(example, repo):
    """`promptdt reproduce` on a user's manifest naming the suite (`[suites.<name>]`, the data the
    README's block collected): the cell trains, is evaluated in the user's environment through the
    worker, and is reported like the paper's cells (docs/reproduce.md, "Your own experiments")."""
    here, _ = example
    manifest = here / "smoke.toml"
    manifest.write_text("""
name = "pendulum_mass_smoke"
title = "Prompt-DT on the pendulum_mass suite"
description = "A user's experiment: one cell, the example's suite."
layout = "table"
[suites.pendulum]
file = "suite.toml"
data = "data"
[budgets.smoke]
note = "seconds"
seeds = 1
iterations = 2
steps_per_iteration = 2
batch_size_per_task = 2
eval_episodes = 1
test_eval_interval = 1
train_eval_interval = 0
save_interval = 1
[[cells]]
env = "pendulum"
method = "prompt-dt"
row = "Prompt-DT"
column = "pendulum_mass"
""")
    # The worker's Python: this one, with promptdt (the suite names none).
    env = dict(os.environ, PROMPTDT_PYTHON=sys.executable)
    out = subprocess.run([str(promptdt_exe(repo)), "reproduce", str(manifest), "--budget", "smoke",
                          "--out", "repro"], cwd=here, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, f"stdout:\n{out.stdout}\nstderr:\n{out.stderr}"
    report = (here / "repro/reports/pendulum_mass_smoke-smoke/report.md").read_text()
    assert "Prompt-DT" in report and "pendulum_mass" in report, report
    # A user's experiment has no paper values: no paper columns, no "paper's claims".
    assert "paper normalised" not in report and "The paper's claims" not in report, report
    evals = (here / "repro/runs/pendulum/prompt-dt/smoke/seed0/eval.jsonl").read_text().splitlines()
    assert {json.loads(e)["task"] for e in evals} == {"pendulum_mass-6", "pendulum_mass-7"}, evals
