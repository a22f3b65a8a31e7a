"""promptdt: the Prompt-based Decision Transformer (Prompt-DT) in Rust, from Python.

A trained run's policy (``Policy``), the environment families as gymnasium environments
(``gymnasium.make("promptdt/CheetahVel-v0", task=3)``, ``promptdt.make_vec``), the dataset readers (``load_dataset``), and training, evaluation and
collection (``train``, ``evaluate``, ``collect``), over the same library code as the ``promptdt``
command. Arrays are numpy arrays. Every error is a ``promptdt.Error`` (``promptdt.errors``) that
names the file, field or shape, and also the built-in exception of its kind (``ValueError``,
``TypeError``, ``FileNotFoundError``, ``OSError``, ``RuntimeError``).
"""
from __future__ import annotations

import json as _json
import os as _os
import sys as _sys
from dataclasses import dataclass as _dataclass
from pathlib import Path as _Path
from typing import Any, Callable, Iterable, List, Optional, Sequence, Union

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
from ._args import _uint  # noqa: E402
from .errors import (  # noqa: E402,F401
    ArgumentTypeError,
    Error,
    FileError,
    InvalidInputError,
    NotFoundError,
    StateError,
)
from ._native import Adaptation, Policy, Prompt, PromptBandit, TaskPlan, families, set_num_threads  # noqa: E402,F401

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


#: What ``train``'s, ``evaluate``'s and ``collect``'s ``progress`` takes: True (a progress line on
#: stderr), False (nothing), or a callable called with each report (a dict).
ProgressArg = Union[bool, Callable[[dict], Any]]


class _ProgressLine:
    """A tqdm-style line on stderr, rewritten in place: what is done, the loss (training) and
    the time left."""

    def __init__(self, what: str):
        self.what = what
        self.first: Optional[int] = None
        self.shown = float("-inf")
        self.open = False

    def __call__(self, p: dict) -> None:
        if "iteration" in p:
            done, total, unit = p["iteration"], p["iterations"], "iterations"
        else:
            done, total, unit = p["done"], p["total"], p["unit"]
        if self.first is None:
            # A resumed run counts from where it stopped; a collection from nothing.
            self.first = done - 1 if "iteration" in p else 0
        elapsed = p["elapsed_s"]
        rate = (done - self.first) / elapsed if elapsed > 0 else 0.0
        eta = (total - done) / rate if rate > 0 else 0.0
        extra = f"  loss {p['loss']:.5f}" if "loss" in p else ""
        if p.get("test_return") is not None:
            extra += f"  test return {p['test_return']:.2f}"
        if done < total and elapsed - self.shown < 0.1:
            return  # at most ten lines a second (a scripted collection reports hundreds)
        self.shown = elapsed
        line = (f"\r{self.what} {done}/{total} {unit}{extra}  "
                f"[{_clock(elapsed)} elapsed, ETA {_clock(eta)}]")
        _sys.stderr.write(line)
        self.open = done < total
        if not self.open:
            _sys.stderr.write("\n")
        _sys.stderr.flush()

    def close(self) -> None:
        """Ends an unfinished line (the call was stopped) so that what follows starts a line."""
        if self.open:
            _sys.stderr.write("\n")
            _sys.stderr.flush()
            self.open = False


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


def _with_progress(progress: ProgressArg, what: str, call: Callable[[Any], Any]) -> Any:
    if progress is True:
        line = _ProgressLine(what)
        try:
            return call(line)
        finally:
            line.close()
    if progress is False or progress is None:
        return call(None)
    if not callable(progress):
        raise ArgumentTypeError(f"progress: expected True, False or a callable, got {progress!r}")
    return call(progress)


def _opt_uint(name: str, value: Any, expected: str, *, low: int = 0) -> Optional[int]:
    """``None``, or a checked integer argument: a ``TypeError``/``ValueError`` naming it, what was
    given and what is expected (never an ``OverflowError`` from the native layer)."""
    if value is None:
        return None
    return _uint(name, value, expected, low=low, high=2**64)


def train(
    out: PathLike,
    config: Optional[PathLike] = None,
    *,
    resume: bool = False,
    seed: Optional[int] = None,
    iterations: Optional[int] = None,
    method: Optional[str] = None,
    device: Optional[str] = None,
    matmul: Optional[str] = None,
    data: Optional[PathLike] = None,
    progress: ProgressArg = True,
    env: Optional[Callable[[dict], Any]] = None,
) -> dict:
    """``promptdt train``: trains from ``config`` (TOML) into ``out``, or continues the run in
    ``out`` exactly where it stopped (``resume=True``; ``iterations`` then sets the run's length).
    Returns ``{"dir", "iterations_done", "finished", "last_test_mean"}``.

    ``matmul``: ``"fp32"``, ``"tf32"`` or ``"bf16"``, how the run computes its matrix products
    (the run's ``run.matmul``; docs/implementation-details.md, C.8). Not with ``resume=True``.

    ``progress``: True (default) shows a line on stderr (iteration, loss, time left), False shows
    nothing, a callable is called after every iteration with ``{"iteration", "iterations",
    "loss", "test_return", "elapsed_s"}`` (an exception it raises stops the run and propagates).
    Ctrl-C stops training before the next gradient step and raises ``KeyboardInterrupt``; the
    iteration under way is dropped, and ``train(out, resume=True)`` goes on from the run's last
    checkpoint or resume point (``train.resume_interval`` sets how often one is written).

    ``env``: a ``factory(task)`` returning a new ``gymnasium.Env`` for one episode (as
    ``evaluate``'s ``env``): the run's periodic evaluations are played in its environments, in
    this process, with the run's protocol, and recorded in ``eval.jsonl`` as any run's. A task
    suite with no ``[environment]`` is then evaluated in them instead of offline. A run resumes
    with evaluations of the kind it began with: one evaluated in a factory's environments on such
    a suite needs ``env=`` again (``train(out, resume=True, env=factory)``), and one evaluated
    offline refuses ``env=``; each refusal an ``InvalidInputError`` naming the run."""
    if env is not None and not callable(env):
        raise ArgumentTypeError(f"env: expected a callable factory(task) -> gymnasium.Env, got {env!r}")
    seed = _opt_uint("seed", seed, "a seed")
    iterations = _opt_uint("iterations", iterations, "a number of iterations")
    return _with_progress(progress, "train", lambda report: _native.train(
        _os.fspath(out),
        config=None if config is None else _os.fspath(config),
        resume=resume,
        seed=seed,
        iterations=iterations,
        method=method,
        matmul=matmul,
        device=device,
        data=None if data is None else _os.fspath(data),
        progress=report,
        env=env,
    ))


def evaluate(
    run: PathLike,
    *,
    episodes: Optional[int] = None,
    split: str = "test",
    device: Optional[str] = None,
    data: Optional[PathLike] = None,
    prompt_strategy: Optional[str] = None,
    prompt_episodes: Optional[int] = None,
    prompt_length: Optional[int] = None,
    adapt: Optional[str] = None,
    adapt_steps: Optional[int] = None,
    adapt_batch: Optional[int] = None,
    progress: ProgressArg = True,
    env: Optional[Callable[[dict], Any]] = None,
) -> dict:
    """``promptdt eval``: the final evaluation of a run's latest checkpoint, also written to the
    run's ``eval_final.json``; returns its content.

    ``prompt_strategy`` (``promptdt eval --prompt-strategy``; docs/prompt-control.md):
    ``reference`` (default), ``random-segment``, ``best-return``, ``nearest-start`` or ``bandit``;
    ``prompt_episodes`` / ``prompt_length``: the test-time prompt's J and H. Other than the
    default, the result goes to ``eval_prompt_<strategy>.json`` and carries ``prompt_strategy``
    and the strategy's ``picks``.

    ``adapt`` (``promptdt eval --adapt``): ``soft-prompt``, ``ptdt`` or ``lora``, each test task
    adapted from its demonstrations first, the backbone frozen (``adapt_steps`` / ``adapt_batch``:
    iterations and demonstration segments per iteration, defaults 20 and 16); the result goes to
    ``eval_adapt_<kind>.json`` and carries ``adapt`` and each task's ``adapt_log``.

    ``progress``: True (default) shows a line on stderr (episodes done, time left), False shows
    nothing, a callable gets ``{"done", "total", "unit": "episodes", "elapsed_s"}`` as episodes end
    (an exception it raises stops the evaluation and propagates). Ctrl-C stops the episodes at
    their next step and raises ``KeyboardInterrupt``; nothing is written then.

    ``env``: a ``factory(task)`` returning a new ``gymnasium.Env`` for one episode, ``task`` a dict
    ``{"index", "name", "params"}`` of the run's family: the episodes are played in its
    environments, in this process, with the run's protocol (episodes, reset seeds, prompts,
    target return, success) and batched across episodes, each request answered by
    ``promptdt.worker.Session(factory)`` as the CLI's worker answers it (docs/python.md). The
    result is returned and nothing is written to the run directory (its files are what the run
    alone reproduces). A factory that raises, spaces of other sizes than the family's, a
    non-finite observation or a ``reset``/``step`` that raises: an ``InvalidInputError`` naming
    the task (and the step).

    A run on a task suite with no ``[environment]`` (and no ``env`` given) plays no episodes: it is
    evaluated offline, the prompted model's action error on the tasks' data, written to
    ``eval_offline.json`` and returned (``metric``: ``action_mse``, lower is better; not a return)."""
    if env is not None and not callable(env):
        raise ArgumentTypeError(f"env: expected a callable factory(task) -> gymnasium.Env, got {env!r}")
    episodes = _opt_uint("episodes", episodes, "a number of episodes")
    adapt_steps = _opt_uint("adapt_steps", adapt_steps, "a number of iterations", low=1)
    adapt_batch = _opt_uint("adapt_batch", adapt_batch, "a number of segments", low=1)
    prompt_episodes = _opt_uint("prompt_episodes", prompt_episodes, "a number of segments", low=1)
    prompt_length = _opt_uint("prompt_length", prompt_length, "a number of steps", low=1)
    text = _with_progress(progress, "evaluate", lambda report: _native.evaluate(
        _os.fspath(run),
        episodes=episodes,
        split=split,
        device=device,
        data=None if data is None else _os.fspath(data),
        prompt_strategy=prompt_strategy,
        prompt_episodes=prompt_episodes,
        prompt_length=prompt_length,
        adapt=adapt,
        adapt_steps=adapt_steps,
        adapt_batch=adapt_batch,
        progress=report,
        env=env,
    ))
    return _json.loads(text)


def pretrained_dir(env: str) -> _Path:
    """The trained agent directory of a MuJoCo family shipped in this package
    (``promptdt/pretrained/<env>``: ``cheetah_dir``, ``cheetah_vel``, ``ant_dir``), the one
    ``collect`` uses by default. Raises ``ValueError`` for an unknown family or one collected with
    scripted policies, ``FileNotFoundError`` when the package was built without the agents."""
    return _shipped_agents(env)


def _shipped_agents(env: str) -> _Path:
    if _native.is_scripted(env):  # raises ValueError naming an unknown family and the known ones
        raise InvalidInputError(f"{env} is collected with scripted policies: it has no agent directory")
    path = _Path(__file__).resolve().parent / "pretrained" / env
    if not (path / "agent.json").is_file():
        raise NotFoundError(
            f"agent directory {path}: not in this installation (scripts/install_python.sh copies "
            "the checkout's pretrained/ into the package); pass pretrained_dir=..."
        )
    return path


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
    progress: ProgressArg = True,
    policy: Optional[Callable[[Any, dict], Any]] = None,
    medium_policy: Optional[Callable[[Any, dict], Any]] = None,
    medium_noise: Optional[float] = None,
    factory: Optional[Callable[[dict], Any]] = None,
    modes: Optional[Sequence[str]] = None,
    tasks: Optional[Sequence[int]] = None,
    envs_per_task: Optional[int] = None,
) -> int:
    """``promptdt collect``: datasets and prompt sets of every task of ``env`` into ``out``.

    A task suite (``env`` a ``suite.toml``; docs/your-own-tasks.md) is collected in its own
    environment from ``policy``, a callable ``policy(obs, task) -> action`` (``obs`` the float32
    observation, ``task`` ``{"index", "name", "params"}``), as ``promptdt collect --env suite.toml
    --policy module:callable`` does, with the same bytes: ``expert`` is the policy (with
    ``action_noise``, in half-ranges of each action dimension, default 0), ``medium``
    ``medium_policy`` (with ``action_noise``) or else the expert with ``medium_noise`` (default
    0.5), ``random`` uniform actions in the suite's bounds; every action clipped into the bounds.
    The prompt sets are each dataset's ``prompt_episodes`` (default 5) episodes of highest
    return. ``factory(task)`` makes each environment (a new ``gymnasium.Env``); without it, the
    suite's ``[environment]`` is made in this process (the suite file's directory first on
    ``sys.path`` meanwhile). ``modes`` (default all three), ``tasks`` (indices, default all) and
    ``envs_per_task`` (environments per task stepped together, default 10; the data do not
    depend on it) choose the work. A policy that raises or returns another shape or NaN, an
    environment that raises or returns NaN: an ``InvalidInputError`` naming the task and step,
    with the files finished before it whole and no card.
    Families with scripted policies (``families()[env]["scripted"]``: ``point_robot``,
    ``metaworld_reach``, ``dial``) use them (reach: the paper's 20 tasks, 200 episodes each by
    default; ``action_noise`` is its expert's noise, 0.2 by default, 0 for the deterministic
    expert; dial: the 10 digits, 200 episodes each); the others (the MuJoCo families) use a trained
    agent directory
    (``pretrained_dir``, default the agents shipped in the package: ``promptdt.pretrained_dir(env)``,
    as ``--from-pretrained``). Returns the number of ``.safetensors`` files written: a dataset and
    a prompt set for every task and mode. An unknown ``env`` raises ``ValueError`` naming the known
    families.

    ``progress``: True (default) shows a line on stderr, False nothing, a callable gets
    ``{"done", "total", "unit": "episodes", "elapsed_s"}`` as episodes are played (the datasets'
    and the prompt sets' episodes; for scripted families at most every 50 ms, for the others
    after each chunk of episodes). Ctrl-C stops it within a step or an episode
    and raises ``KeyboardInterrupt``; the files already written are whole, ``dataset.json`` (the
    card) is written only by a call that finishes: collect again to finish."""
    seed = _uint("seed", seed, "a seed", high=2**64)
    episodes = _opt_uint("episodes", episodes, "a number of episodes")
    prompt_episodes = _opt_uint("prompt_episodes", prompt_episodes, "a number of episodes")
    if str(env).endswith(".toml"):
        return _collect_suite(env, out, seed=seed, episodes=episodes,
                              prompt_episodes=prompt_episodes, action_noise=action_noise,
                              progress=progress, policy=policy, medium_policy=medium_policy,
                              medium_noise=medium_noise, factory=factory, modes=modes,
                              tasks=tasks, envs_per_task=envs_per_task)
    suite_only = {"policy": policy, "medium_policy": medium_policy, "medium_noise": medium_noise,
                  "factory": factory, "modes": modes, "tasks": tasks,
                  "envs_per_task": envs_per_task}
    given = [k for k, v in suite_only.items() if v is not None]
    if given:
        raise InvalidInputError(f"{', '.join(given)}: for a task suite (a suite.toml), not for "
                                f"{env}, which collects with its own policies")
    scripted = _native.is_scripted(env)  # raises ValueError naming an unknown family
    if scripted:
        return _with_progress(progress, f"collect {env}", lambda report: _native.collect_scripted(
            env,
            _os.fspath(out),
            seed=seed,
            episodes=episodes,
            prompt_episodes=prompt_episodes,
            action_noise=action_noise,
            progress=report,
        ))
    agents = _shipped_agents(env) if pretrained_dir is None else pretrained_dir
    return _with_progress(progress, f"collect {env}", lambda report: _native.collect_from_agent(
        _os.fspath(agents),
        _os.fspath(out),
        seed=seed,
        episodes=episodes,
        prompt_episodes=prompt_episodes,
        device=device,
        progress=report,
    ))


def _callable_name(f: Any) -> str:
    """``module:qualname`` of a callable: what ``promptdt collect --policy`` names it by, so
    both record the same policy in the dataset card."""
    module = getattr(f, "__module__", None) or type(f).__module__
    name = getattr(f, "__qualname__", None) or type(f).__qualname__
    return f"{module}:{name}"


def _collect_suite(suite: PathLike, out: PathLike, *, seed: int, episodes: Optional[int],
                   prompt_episodes: Optional[int], action_noise: Optional[float],
                   progress: ProgressArg, policy: Any, medium_policy: Any,
                   medium_noise: Optional[float], factory: Any, modes: Optional[Sequence[str]],
                   tasks: Optional[Sequence[int]], envs_per_task: Optional[int]) -> int:
    for name, f in (("policy", policy), ("medium_policy", medium_policy), ("factory", factory)):
        if f is not None and not callable(f):
            raise ArgumentTypeError(f"{name}: expected a callable, got {f!r}")
    if policy is None:
        raise InvalidInputError(f"{suite} is a task suite: collecting its data needs "
                                "policy=callable(obs, task) (docs/your-own-tasks.md)")
    envs_per_task = _opt_uint("envs_per_task", envs_per_task, "a number of environments", low=1)
    tasks = None if tasks is None else [_uint("tasks", t, "a task index", high=2**32) for t in tasks]
    if isinstance(modes, str):
        modes = modes.split(",")
    # The suite's own `module:callable` beside the suite file imports as in a worker process.
    where = str(_Path(suite).resolve().parent)
    added = factory is None and where not in _sys.path
    if added:
        _sys.path.insert(0, where)
    try:
        return _with_progress(progress, f"collect {suite}", lambda report: _native.collect_policy(
            _os.fspath(suite),
            _os.fspath(out),
            policy,
            _callable_name(policy),
            medium_policy=medium_policy,
            medium_name=None if medium_policy is None else _callable_name(medium_policy),
            factory=factory,
            seed=seed,
            episodes=episodes,
            prompt_episodes=prompt_episodes,
            modes=None if modes is None else list(modes),
            tasks=tasks,
            action_noise=action_noise,
            medium_noise=medium_noise,
            envs_per_task=envs_per_task,
            progress=report,
        ))
    finally:
        if added and where in _sys.path:
            _sys.path.remove(where)


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
        raise NotFoundError(
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
        raise StateError(
            f"promptdt reproduce {experiment} --budget {budget} failed "
            f"(exit {done.returncode}): {done.stderr.strip()[-2000:]}"
        )
    if only is not None:
        return None
    report = out / "reports" / f"{experiment}-{budget}" / "report.json"
    return _json.loads(report.read_text())


# Minari interop (``promptdt.minari_io``): its functions themselves, typed; minari is imported only
# when one is called.
from .minari_io import export_minari, import_minari  # noqa: E402


def write_dataset(path: PathLike, dataset: "Dataset") -> None:
    """Writes ``dataset`` as a native ``.safetensors`` file, atomically, after the reader's checks.
    A dataset that names its family (``dataset.env``: a family's name, or the path of a task suite
    file, ``docs/your-own-tasks.md``) must have that family's ``obs_dim`` and ``act_dim``
    (``ValueError`` otherwise, also for an unknown family or a bad suite file); the file records
    the family's name (a suite's ``name``). A missing directory raises ``FileNotFoundError``."""
    trajs = [
        dict(observations=t.observations, actions=t.actions, rewards=t.rewards,
             terminated=t.terminated, truncated=t.truncated)
        for t in dataset.trajectories
    ]
    _native.write_dataset(_os.fspath(path), trajs, dataset.obs_dim, dataset.act_dim,
                          env=dataset.env, task=dataset.task, mode=dataset.mode)


@_dataclass
class FlatDataset:
    """Every step of a multi-task dataset in flat arrays, as d3rlpy's ``MDPDataset`` and other
    offline RL libraries take them (``d3rlpy.dataset.MDPDataset(observations=..., actions=...,
    rewards=..., terminals=..., timeouts=...)``). Step ``i`` belongs to task ``task_ids[i]``; an
    episode ends at a step whose ``terminals`` or ``timeouts`` is set."""

    observations: _np.ndarray  # [N, obs_dim] float32: the observation before actions[i]
    actions: _np.ndarray  # [N, act_dim] float32
    rewards: _np.ndarray  # [N] float32
    terminals: _np.ndarray  # [N] bool: the MDP ended after step i
    timeouts: _np.ndarray  # [N] bool: a time limit cut the episode after step i
    task_ids: _np.ndarray  # [N] int64: the task of step i
    env: Optional[str] = None
    mode: Optional[str] = None

    def __len__(self) -> int:
        return len(self.rewards)

    @property
    def episode_starts(self) -> _np.ndarray:
        """The index of each episode's first step."""
        ends = _np.flatnonzero(self.terminals | self.timeouts)
        return _np.concatenate([[0], ends[:-1] + 1]).astype(_np.int64) if len(ends) else ends


def flat_dataset(
    source: Union[PathLike, Iterable[Dataset]],
    *,
    mode: str = "expert",
    tasks: Optional[Sequence[int]] = None,
    env: Optional[str] = None,
) -> FlatDataset:
    """The ``mode`` files (``expert``, ``prompt-expert``, ...) of the directory ``source`` (what
    ``collect`` wrote, or the reference release's pickles; ``tasks``: a subset; ``env``: the
    family where the directory holds several), or a sequence of ``Dataset`` objects (each with its
    ``task``), as one :class:`FlatDataset`. The arrays are concatenated in task order."""
    if isinstance(source, (str, _os.PathLike)):
        from .minari_io import _task_files

        files = _task_files(source, mode, tasks, env)
        env = files[0][0]
        flat_mode: Optional[str] = mode
        parts = [(task, load_dataset(path)) for _, task, path in files]
    else:
        parts = []
        for i, ds in enumerate(source):
            if not isinstance(ds, Dataset):
                raise ArgumentTypeError(f"source[{i}]: expected a promptdt.Dataset, got {type(ds).__name__}")
            if ds.task is None:
                raise InvalidInputError(f"source[{i}]: the dataset names no task (a reference pickle): "
                                 "pass the directory instead")
            parts.append((ds.task, ds))
        if not parts:
            raise InvalidInputError("source: no datasets")
        envs = {ds.env for _, ds in parts}
        if len(envs) > 1:
            raise InvalidInputError(f"source: datasets of several families ({sorted(map(str, envs))})")
        env = envs.pop()
        modes = {ds.mode for _, ds in parts}
        flat_mode = modes.pop() if len(modes) == 1 else None
    dims = {(ds.obs_dim, ds.act_dim) for _, ds in parts}
    if len(dims) > 1:
        raise InvalidInputError(f"source: datasets of different (obs_dim, act_dim): {sorted(dims)}")
    trajs = [(task, t) for task, ds in parts for t in ds.trajectories]
    obs_dim, act_dim = dims.pop()

    def cat(field: str, shape: tuple, dtype) -> _np.ndarray:
        if not trajs:
            return _np.zeros(shape, dtype)
        return _np.concatenate([getattr(t, field) for _, t in trajs]).astype(dtype, copy=False)

    return FlatDataset(
        observations=cat("observations", (0, obs_dim), _np.float32),
        actions=cat("actions", (0, act_dim), _np.float32),
        rewards=cat("rewards", (0,), _np.float32),
        terminals=cat("terminated", (0,), bool),
        timeouts=cat("truncated", (0,), bool),
        task_ids=_np.concatenate([_np.full(len(t), task, _np.int64) for task, t in trajs])
        if trajs else _np.zeros(0, _np.int64),
        env=env,
        mode=flat_mode,
    )


__all__ = [
    "FlatDataset",
    "flat_dataset",
    "pretrained_dir",
    "export_minari",
    "import_minari",
    "write_dataset",
    "Dataset",
    "Policy",
    "Prompt",
    "PromptBandit",
    "Adaptation",
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
    "Error",
    "InvalidInputError",
    "ArgumentTypeError",
    "FileError",
    "NotFoundError",
    "StateError",
]
if "make_vec" in globals():  # with gymnasium (above)
    __all__ += ["make_vec"]
