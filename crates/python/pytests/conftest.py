"""Fixtures: a tiny trained point-robot run (collected and trained through the package itself)."""
import os
import pathlib

import pytest

import promptdt

REPO = pathlib.Path(__file__).resolve().parents[3]


@pytest.fixture(scope="session")
def repo() -> pathlib.Path:
    return REPO


@pytest.fixture(scope="session")
def point_data(tmp_path_factory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("data") / "point_robot"
    n = promptdt.collect("point_robot", out, seed=0, episodes=20, prompt_episodes=5)
    assert n > 0
    return out


@pytest.fixture(scope="session")
def point_run(tmp_path_factory, point_data) -> pathlib.Path:
    """Prompt-DT on the point robot, 4 iterations of 10 steps (1 libtorch thread: the actions are
    then the same bits in every process on this machine)."""
    root = tmp_path_factory.mktemp("runs")
    config = root / "tiny.toml"
    text = (REPO / "configs/point_robot/demo.toml").read_text()
    text = text.replace("iterations = 40", "iterations = 4").replace("save_interval = 20", "save_interval = 2")
    text = text.replace("test_eval_interval = 5", "test_eval_interval = 2").replace("episodes = 20", "episodes = 3")
    text = text.replace("[run]\n", "[run]\nthreads = 1\ndevice = \"cpu\"\n")
    config.write_text(text)
    out = root / "prompt-dt"
    summary = promptdt.train(out, config, data=point_data)
    assert summary["finished"] and summary["iterations_done"] == 4
    return out
