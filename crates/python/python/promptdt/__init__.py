"""promptdt: the Prompt-based Decision Transformer (Prompt-DT) in Rust, from Python.

A trained run's policy (``Policy``), the environment families as gymnasium environments
(``gymnasium.make("promptdt/CheetahVel-v0", task=3)``, ``promptdt.make_vec``), the dataset readers (``load_dataset``), and training, evaluation and
collection (``train``, ``evaluate``, ``collect``), over the same library code as the ``promptdt``
command. Arrays are numpy arrays; errors are Python exceptions (``ValueError``,
``FileNotFoundError``) that name the file, field or shape.
"""
from __future__ import annotations

import json as _json
import os as _os
import sys as _sys
from dataclasses import dataclass as _dataclass
from pathlib import Path as _Path
from typing import List, Optional, Union

import numpy as _np

_TORCH = "2.11.0"
# The module links the libtorch bundled in promptdt/_libs. A PyTorch imported before it provides
# libtorch_cpu.so under the same name, and the dynamic loader then uses that one: it must be the
# same version, or the process would mix two libtorch builds.
if "torch" in _sys.modules:
    _v = getattr(_sys.modules["torch"], "__version__", "").split("+")[0]
    if _v and _v != _TORCH:
        raise ImportError(
            f"promptdt is built on libtorch {_TORCH}, but torch {_v} is already imported in this "
            "process; import promptdt first, or use torch 2.11.0"
        )

from . import _native  # noqa: E402
from ._native import Policy, Prompt, TaskPlan, families, set_num_threads  # noqa: E402,F401

__version__ = _native.__version__

# gymnasium is optional: with it, `import promptdt` registers the families' gymnasium ids
# (`promptdt/CheetahVel-v0`, ...: promptdt.envs.ENV_IDS) and offers `promptdt.make_vec`.
try:
    import gymnasium as _gymnasium  # noqa: F401
except ImportError:  # pragma: no cover - exercised only without gymnasium
    pass
else:
    from .envs import make_vec as make_vec  # noqa: E402
    from .envs import register_envs as _register_envs  # noqa: E402

    _register_envs()

PathLike = Union[str, "_os.PathLike[str]"]


@_dataclass
class Trajectory:
    """One episode: ``observations[t]`` is the observation before ``actions[t]``."""

    observations: _np.ndarray  # [T, obs_dim] float32
    actions: _np.ndarray  # [T, act_dim] float32
    rewards: _np.ndarray  # [T] float32
    terminated: _np.ndarray  # [T] bool: the MDP ended here
    truncated: _np.ndarray  # [T] bool: a time limit cut the episode here

    def __len__(self) -> int:
        return len(self.rewards)

    @property
    def episode_return(self) -> float:
        return float(self.rewards.astype(_np.float64).sum())


@_dataclass
class Dataset:
    """The trajectories of one file (one task's D_i or prompt set P_i)."""

    obs_dim: int
    act_dim: int
    trajectories: List[Trajectory]
    #: family, task index and mode (``expert``, ``prompt-expert``, ...) of a native file; None for
    #: a reference pickle (its name says them)
    env: Optional[str] = None
    task: Optional[int] = None
    mode: Optional[str] = None

    def __len__(self) -> int:
        return len(self.trajectories)


def load_dataset(path: PathLike) -> Dataset:
    """Reads a dataset file: a native ``.safetensors`` file (``promptdt collect``) or a reference
    release ``.pkl`` (read by promptdt's safe reader: nothing in the file is executed). The arrays
    are handed over without a copy."""
    d = _native.load_dataset(_os.fspath(path))
    meta = d["meta"] or {}
    return Dataset(
        obs_dim=d["obs_dim"],
        act_dim=d["act_dim"],
        trajectories=[Trajectory(**t) for t in d["trajectories"]],
        env=meta.get("env"),
        task=meta.get("task"),
        mode=meta.get("mode"),
    )


def task_params(family: str, task: int) -> dict:
    """A task's parameters (``{"velocity": v}``, ``{"goal": [x, y]}``, ...)."""
    return _json.loads(_native.task_params(family, task))


def train(
    out: PathLike,
    config: Optional[PathLike] = None,
    *,
    resume: bool = False,
    seed: Optional[int] = None,
    iterations: Optional[int] = None,
    method: Optional[str] = None,
    device: Optional[str] = None,
    data: Optional[PathLike] = None,
) -> dict:
    """``promptdt train``: trains from ``config`` (TOML) into ``out``, or continues the run in
    ``out`` exactly where it stopped (``resume=True``). Returns ``{"dir", "iterations_done",
    "finished", "last_test_mean"}``."""
    return _native.train(
        _os.fspath(out),
        config=None if config is None else _os.fspath(config),
        resume=resume,
        seed=seed,
        iterations=iterations,
        method=method,
        device=device,
        data=None if data is None else _os.fspath(data),
    )


def evaluate(
    run: PathLike,
    *,
    episodes: Optional[int] = None,
    split: str = "test",
    device: Optional[str] = None,
    data: Optional[PathLike] = None,
) -> dict:
    """``promptdt eval``: the final evaluation of a run's latest checkpoint, also written to the
    run's ``eval_final.json``; returns its content."""
    return _json.loads(
        _native.evaluate(
            _os.fspath(run),
            episodes=episodes,
            split=split,
            device=device,
            data=None if data is None else _os.fspath(data),
        )
    )


def collect(
    env: str,
    out: PathLike,
    *,
    seed: int = 0,
    episodes: Optional[int] = None,
    prompt_episodes: Optional[int] = None,
    pretrained_dir: Optional[PathLike] = None,
    device: str = "cpu",
    action_noise: Optional[float] = None,
) -> int:
    """``promptdt collect``: datasets and prompt sets of every task of ``env`` into ``out``.
    Families with scripted policies (``families()[env]["scripted"]``: ``point_robot``,
    ``metaworld_reach``, ``dial``) use them (reach: the paper's 20 tasks, 200 episodes each by
    default; ``action_noise`` is its expert's noise, 0.2 by default, 0 for the deterministic
    expert; dial: the 10 digits, 200 episodes each); the others (the MuJoCo families) use a trained
    agent directory
    (``pretrained_dir``, default ``pretrained/<env>`` of the checkout, as ``--from-pretrained``).
    Returns the number of files written."""
    if _native.is_scripted(env):
        return _native.collect_scripted(
            env,
            _os.fspath(out),
            seed=seed,
            episodes=episodes,
            prompt_episodes=prompt_episodes,
            action_noise=action_noise,
        )
    if pretrained_dir is None:
        pretrained_dir = _Path("pretrained") / env
    return _native.collect_from_agent(
        _os.fspath(pretrained_dir),
        _os.fspath(out),
        seed=seed,
        episodes=episodes,
        prompt_episodes=prompt_episodes,
        device=device,
    )


def experiments() -> list:
    """``promptdt reproduce --list``: every committed experiment (``fig2``, ``table1``, ...) with its
    cells and, per budget (``paper``, ``cpu``, ``smoke``), its runs, iterations and stated cost."""
    return _json.loads(_native.experiments())


def reproduce(
    experiment: str,
    *,
    budget: str = "cpu",
    out: PathLike = "runs/repro",
    seeds: Optional[int] = None,
    jobs: Optional[int] = None,
    threads: Optional[int] = None,
    device: Optional[str] = None,
    data_root: Optional[PathLike] = None,
    pretrained_root: Optional[PathLike] = None,
    only: Optional[str] = None,
    report_only: bool = False,
    exe: Optional[PathLike] = None,
) -> Optional[dict]:
    """``promptdt reproduce``: runs what is unfinished of a paper artifact at a budget, then writes
    its report under ``out/reports/<experiment>-<budget>/`` and returns ``report.json`` (``None``
    with ``only``, which runs one run and writes no report).

    The sweep starts the ``promptdt`` binary once per run (as the CLI does, so a killed sweep
    resumes and runs can be spread over machines), so it needs that binary: ``exe``, else
    ``$PROMPTDT_BIN``, else ``promptdt`` on ``PATH`` (``cargo build --release -p promptdt`` makes
    ``target/release/promptdt``). Raises ``RuntimeError`` with the command's error output when it
    fails."""
    import shutil as _shutil
    import subprocess as _subprocess

    binary = exe or _os.environ.get("PROMPTDT_BIN") or _shutil.which("promptdt")
    if binary is None or not _Path(binary).is_file():
        raise FileNotFoundError(
            "reproduce needs the promptdt binary: pass exe=..., set PROMPTDT_BIN, or put promptdt "
            f"on PATH (cargo build --release -p promptdt); got {binary!r}"
        )
    out = _Path(out)
    args = [_os.fspath(binary), "reproduce", experiment, "--budget", budget, "--out", _os.fspath(out)]
    for flag, value in (
        ("--seeds", seeds),
        ("--jobs", jobs),
        ("--threads", threads),
        ("--device", device),
        ("--data-root", data_root),
        ("--pretrained-root", pretrained_root),
        ("--only", only),
    ):
        if value is not None:
            args += [flag, _os.fspath(value) if isinstance(value, _os.PathLike) else str(value)]
    if report_only:
        args.append("--report-only")
    done = _subprocess.run(args, stdin=_subprocess.DEVNULL, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(
            f"promptdt reproduce {experiment} --budget {budget} failed "
            f"(exit {done.returncode}): {done.stderr.strip()[-2000:]}"
        )
    if only is not None:
        return None
    report = out / "reports" / f"{experiment}-{budget}" / "report.json"
    return _json.loads(report.read_text())


def export_minari(*args, **kwargs):
    """promptdt files -> a Minari dataset (see ``promptdt.minari_io.export_minari``)."""
    from .minari_io import export_minari as f

    return f(*args, **kwargs)


def import_minari(*args, **kwargs):
    """A Minari dataset -> promptdt files (see ``promptdt.minari_io.import_minari``)."""
    from .minari_io import import_minari as f

    return f(*args, **kwargs)


def write_dataset(path: PathLike, dataset: "Dataset") -> None:
    """Writes ``dataset`` as a native ``.safetensors`` file, atomically, after the reader's checks."""
    trajs = [
        dict(observations=t.observations, actions=t.actions, rewards=t.rewards,
             terminated=t.terminated, truncated=t.truncated)
        for t in dataset.trajectories
    ]
    _native.write_dataset(_os.fspath(path), trajs, dataset.obs_dim, dataset.act_dim,
                          env=dataset.env, task=dataset.task, mode=dataset.mode)


__all__ = [
    "export_minari",
    "import_minari",
    "write_dataset",
    "Dataset",
    "Policy",
    "Prompt",
    "TaskPlan",
    "Trajectory",
    "collect",
    "evaluate",
    "experiments",
    "families",
    "load_dataset",
    "reproduce",
    "set_num_threads",
    "task_params",
    "train",
]
