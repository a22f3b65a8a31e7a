"""Minari interop: promptdt datasets to Minari datasets and back, through the ``minari`` library.

Minari (the maintained successor of D4RL) stores episodes with ``T + 1`` observations (the one after
the last action included). promptdt's files keep the ``T`` observations before each action: the one
after the last action was not recorded. The export therefore repeats the last observation and says
so in every episode's options (``"final_observation": "repeated"``) and in the dataset's metadata. A
learner that bootstraps from the last step's next observation must not use it (for time-limit
truncations D4RL-style pipelines drop that step anyway). The import drops the extra observation, so
promptdt -> Minari -> promptdt gives back the same bits.

Per episode, the options hold the task index, its parameters (``{"velocity": 0.3}``), the split it
belongs to (``train``/``test`` of the family's named split) and the set (``expert``,
``prompt-expert``, ...); the import regroups episodes into one native file per task and set.

The export records the family's gymnasium environment (``promptdt/CheetahVel-v0``, the first
exported task as its ``task`` keyword), so ``dataset.recover_environment()`` works wherever the
``promptdt/...`` ids are registered with gymnasium; ``recover_environment(task=t)`` gives another
task.
"""
from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from . import _native
from .errors import InvalidInputError, NotFoundError

if TYPE_CHECKING:  # minari is imported when a function here is called, not with the package
    from minari import MinariDataset  # type: ignore[import-untyped]  # (minari 0.5 has no py.typed)

PathLike = Union[str, "os.PathLike[str]"]
_NAME = re.compile(r"^(?P<env>.+?)-(?P<task>\d+)-(?P<mode>[A-Za-z][\w-]*)\.(safetensors|pkl)$")


def _minari() -> Any:
    try:
        import minari
    except ImportError as e:
        raise ImportError(
            "Minari interop needs the minari package with a storage backend: "
            "pip install 'minari[hdf5]' (or PROMPTDT_PY_EXTRAS=minari bash scripts/install_python.sh)"
        ) from e
    return minari


def _task_files(
    data: PathLike, mode: str, tasks: Optional[Sequence[int]], env: Optional[str] = None
) -> List[Tuple[str, int, Path]]:
    """The ``mode`` files of ``data``, one per task, of one family: ``env``, else the only family
    with files there (or, with ``tasks``, the only one with a file for each of them)."""
    data = Path(data)
    if not data.is_dir():
        raise NotFoundError(f"{data}: not a directory of dataset files")
    if env is not None and env not in _native.families():
        raise InvalidInputError(f"env: unknown family `{env}` (known: {', '.join(_native.families())})")
    by_env: Dict[str, Dict[int, Path]] = {}
    for p in sorted(data.iterdir()):
        m = _NAME.match(p.name)
        if not m or m.group("mode") != mode:
            continue
        found = by_env.setdefault(m.group("env"), {})
        task = int(m.group("task"))
        if task in found and found[task].suffix == ".safetensors":
            continue  # the native file wins over a pickle of the same task, as `auto` picks it
        found[task] = p
    if env is None and len(by_env) > 1:
        fits = [e for e in by_env if tasks is not None and all(t in by_env[e] for t in tasks)]
        if len(fits) != 1:
            raise InvalidInputError(
                f"{data}: files of several families ({', '.join(sorted(by_env))}) for mode {mode}; "
                "give env=... to pick one"
            )
        env = fits[0]
    if env is None:
        env = next(iter(by_env), None)
    found = by_env.get(env, {}) if env is not None else {}
    if tasks is not None:
        missing = [t for t in tasks if t not in found]
        if missing:
            raise InvalidInputError(f"{data}: no {mode} file for tasks {missing}" + (f" of {env}" if env else ""))
        found = {t: found[t] for t in tasks}
    if not found or env is None:  # (no family: no files)
        name = env or "{env}"
        raise InvalidInputError(f"{data}: no `{name}-{{task}}-{mode}.safetensors` (or .pkl) files")
    return [(env, t, p) for t, p in sorted(found.items())]


def _env_spec(family: str, task: int) -> Any:
    """The gymnasium spec ``import promptdt`` registered for ``family`` (``promptdt.envs.env_id``),
    with ``task`` as its keyword."""
    import gymnasium as gym

    # Imported here: promptdt.envs needs gymnasium, which the export needs anyway.
    from .envs import env_id, register_envs

    gid = env_id(family)
    if gid not in gym.registry:  # the registration was removed since the import: again
        register_envs()
    spec = gym.spec(gid)
    return dataclasses.replace(spec, kwargs={**spec.kwargs, "task": task})


def export_minari(
    data: PathLike,
    dataset_id: str,
    *,
    mode: str = "expert",
    tasks: Optional[Sequence[int]] = None,
    split: str = "default",
    author: Optional[str] = None,
    author_email: Optional[str] = None,
    description: Optional[str] = None,
    env: Optional[str] = None,
) -> "MinariDataset":
    """Writes the ``mode`` files of ``data`` (a directory ``promptdt collect`` wrote, or the
    reference release's pickles) as the Minari dataset ``dataset_id`` (under
    ``MINARI_DATASETS_PATH``, default ``~/.minari/datasets``). ``tasks``: a subset; ``env``: the
    family, where ``data`` holds files of several (the reference prompt folder). The dataset
    records the family's gymnasium environment (``env_spec``, see the module docs). Returns the
    ``MinariDataset``."""
    minari = _minari()
    import gymnasium as gym

    files = _task_files(data, mode, tasks, env)
    env = files[0][0]
    fams = _native.families()
    if env not in fams:
        raise InvalidInputError(f"{env}: not a promptdt family ({', '.join(fams)})")
    fam = fams[env]
    if split not in fam["splits"]:
        raise InvalidInputError(f"unknown split `{split}` of {env} (known: {', '.join(fam['splits'])})")
    train, test = (set(x) for x in fam["splits"][split])
    buffers: List[Any] = []
    obs_dim, act_dim = int(fam["obs_dim"]), int(fam["act_dim"])
    for _, task, path in files:
        ds = _native.load_dataset(os.fspath(path))
        if (ds["obs_dim"], ds["act_dim"]) != (obs_dim, act_dim):
            raise InvalidInputError(
                f"{path}: obs_dim {ds['obs_dim']} and act_dim {ds['act_dim']}, but {env} has "
                f"obs_dim {obs_dim} and act_dim {act_dim}"
            )
        which = "train" if task in train else "test" if task in test else "none"
        options = {
            "task": task,
            "task_params": json.loads(_native.task_params(env, task)),
            "split": which,
            "mode": mode,
            "final_observation": "repeated",
        }
        for t in ds["trajectories"]:
            obs = t["observations"]
            buffers.append(
                minari.data_collector.EpisodeBuffer(
                    id=len(buffers),
                    observations=np.concatenate([obs, obs[-1:]]),
                    actions=t["actions"],
                    rewards=t["rewards"],
                    terminations=t["terminated"],
                    truncations=t["truncated"],
                    options=dict(options),
                )
            )
    # The family's action box, per dimension, from Rust (`EnvFamily::action_bounds`).
    low = np.asarray(fam["action_low"], np.float32)
    high = np.asarray(fam["action_high"], np.float32)
    spec = _env_spec(env, files[0][1])
    dataset = minari.create_dataset_from_buffers(
        dataset_id=dataset_id,
        buffer=buffers,
        env=spec,
        eval_env=spec,
        observation_space=gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32),
        action_space=gym.spaces.Box(low, high, (act_dim,), np.float32),
        algorithm_name="promptdt collect",
        author=author or "promptdt",
        author_email=author_email or "https://github.com/promptdt/promptdt/issues",
        code_permalink="https://github.com/promptdt/promptdt",
        description=description
        or f"promptdt {env} {mode} data, {len(files)} tasks (split `{split}`); the last "
        "observation of each episode is a repeat (not recorded)",
    )
    dataset.storage.update_metadata(
        {
            "promptdt_env": env,
            "promptdt_mode": mode,
            "promptdt_split": split,
            "promptdt_tasks": [t for _, t, _ in files],
            "promptdt_final_observation": "repeated",
        }
    )
    return dataset


def import_minari(
    dataset: Union[str, "MinariDataset"],
    out: PathLike,
    *,
    env: Optional[str] = None,
    task: Optional[Union[int, str]] = None,
    mode: Optional[str] = None,
    task_field: str = "task",
    prompt_rule: Optional[str] = None,
) -> List[Path]:
    """Writes a Minari dataset (an id or a ``MinariDataset``) as native files in ``out``, one per
    task and set, for the family ``env``: a built-in family's name or a task suite file's path
    (``suite.toml``; files are named after the suite's ``name``). The observation after each
    episode's last action is dropped.

    The task of each episode: ``task`` (an index or, for a suite, a task's name) for a dataset of
    one task; else the episode's ``task_field`` (default ``"task"``), looked up first in its reset
    options, then in its infos (its first step's value): an index, or a suite task's name. A
    promptdt export carries both ``task`` and ``mode`` in its options and its family in its
    metadata, so ``env`` may be left out. ``mode``: the sets' mode (``expert``, ...), else each
    episode's ``mode`` option. ``prompt_rule`` (``"best:N"``): also write each task's prompt set
    ``{name}-{task}-prompt-{mode}`` of its N highest-return episodes (as ``promptdt data import``
    does). Everything is read and checked against the family before the first file is written.
    Returns the files."""
    minari = _minari()
    if isinstance(dataset, str):
        dataset = minari.load_dataset(dataset)
    meta = dataset.storage.metadata
    env = env or meta.get("promptdt_env")
    if env is None:
        raise InvalidInputError(
            "the dataset was not exported by promptdt: give env (a family or a suite file) and "
            "the task of its episodes (task=..., or task_field=... naming their options' or infos' key)"
        )
    fam = _native.family_info(env)  # raises the library's error naming a bad suite or family
    name, names = fam["name"], list(fam["task_names"])
    fixed = None if task is None else _task_index(task, names, env, "task")
    groups: Dict[Tuple[int, str], List[dict]] = {}
    episode_meta = list(dataset.storage.get_episode_metadata(dataset.episode_indices))
    for ep, em in zip(dataset.iterate_episodes(), episode_meta):
        opts = em.get("options") or {}
        t = fixed if fixed is not None else _episode_task(ep, opts, task_field, names, env)
        m = mode or opts.get("mode")
        if m is None:
            raise InvalidInputError(f"episode {ep.id}: no mode in its options; give mode=...")
        obs = np.asarray(ep.observations)
        if obs.ndim != 2 or len(obs) != len(ep.rewards) + 1:
            raise InvalidInputError(
                f"episode {ep.id}: observations of shape {obs.shape} for {len(ep.rewards)} steps "
                "(promptdt takes Box observations, T + 1 of them)"
            )
        groups.setdefault((t, str(m)), []).append(
            {
                "observations": obs[:-1],
                "actions": np.asarray(ep.actions),
                "rewards": np.asarray(ep.rewards),
                "terminated": np.asarray(ep.terminations, dtype=bool),
                "truncated": np.asarray(ep.truncations, dtype=bool),
            }
        )
    # Every group checked against the family before anything is written.
    for (t, m), trajs in groups.items():
        obs, act = trajs[0]["observations"], trajs[0]["actions"]
        if obs.ndim != 2 or act.ndim != 2:
            raise InvalidInputError(
                f"task {t} ({m}): observations {obs.shape} and actions {act.shape}; promptdt takes "
                "[T, dim] Box observations and actions"
            )
        _native.check_dims(env, obs.shape[1], act.shape[1])
    writes = []
    for (t, m), trajs in sorted(groups.items()):
        writes.append((f"{name}-{t}-{m}.safetensors", t, m, trajs))
        if prompt_rule is not None:
            returns = [float(np.sum(tr["rewards"], dtype=np.float64)) for tr in trajs]
            best = [trajs[i] for i in _native.prompt_indices(returns, prompt_rule)]
            writes.append((f"{name}-{t}-prompt-{m}.safetensors", t, f"prompt-{m}", best))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for file, t, m, trajs in writes:
        path = out / file
        obs_dim = trajs[0]["observations"].shape[1]
        act_dim = trajs[0]["actions"].shape[1]
        _native.write_dataset(os.fspath(path), trajs, obs_dim, act_dim, env=env, task=t, mode=m)
        written.append(path)
    return written


def _task_index(value: Any, names: List[str], env: str, where: str) -> int:
    """A task given by its index or (a suite's) name, checked against the family's tasks."""
    if isinstance(value, (bool, np.bool_)):
        value = None  # a flag is no task
    elif isinstance(value, (int, np.integer)) and 0 <= int(value) < len(names):
        return int(value)
    elif isinstance(value, str) and value in names:
        return names.index(value)
    raise InvalidInputError(
        f"{where}: {value!r} is no task of {env} (tasks 0..{len(names) - 1}"
        + (f": {', '.join(names)})" if names != [str(i) for i in range(len(names))] else ")")
    )


def _episode_task(ep: Any, opts: Dict[str, Any], field: str, names: List[str], env: str) -> int:
    """An episode's task from its reset options' ``field``, else its infos' (first step)."""
    if field in opts:
        return _task_index(opts[field], names, env, f"episode {ep.id}: options[{field!r}]")
    infos = getattr(ep, "infos", None) or {}
    if field in infos and len(infos[field]) > 0:
        value = np.asarray(infos[field])[0]
        value = value.item() if isinstance(value, np.generic) else value
        return _task_index(value, names, env, f"episode {ep.id}: infos[{field!r}]")
    raise InvalidInputError(
        f"episode {ep.id}: no task label: no {field!r} in its options or infos (give task=... for a "
        "dataset of one task, or task_field=... naming the key that holds each episode's task)"
    )


def _main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m promptdt.minari_io DATASET OUT --env ...``: what ``promptdt data import --minari``
    runs (the CLI has no Minari of its own); one line per file written."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m promptdt.minari_io", description=import_minari.__doc__)
    p.add_argument("dataset")
    p.add_argument("out")
    p.add_argument("--env")
    p.add_argument("--task")
    p.add_argument("--mode")
    p.add_argument("--task-field", default="task")
    p.add_argument("--prompt-rule")
    a = p.parse_args(argv)
    task: Optional[Union[int, str]] = a.task
    if a.task is not None and a.task.isdigit():
        task = int(a.task)
    try:
        written = import_minari(a.dataset, a.out, env=a.env, task=task, mode=a.mode,
                                task_field=a.task_field, prompt_rule=a.prompt_rule)
    except (ValueError, OSError, ImportError) as e:
        print(f"error: {e}", file=__import__("sys").stderr)
        return 2
    for path in written:
        print(path)
    return 0


__all__ = ["export_minari", "import_minari"]

if __name__ == "__main__":
    raise SystemExit(_main())
