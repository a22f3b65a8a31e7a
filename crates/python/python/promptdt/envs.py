"""promptdt's environment families as gymnasium environments.

``import promptdt`` registers one gymnasium id per family (``promptdt/CheetahVel-v0``,
``promptdt/PointRobot-v0``, ...: ``promptdt.envs.ENV_IDS``), the task as a keyword::

    env = gymnasium.make("promptdt/CheetahVel-v0", task=3)              # a single gymnasium.Env
    venv = gymnasium.make_vec("promptdt/CheetahVel-v0", num_envs=8, task=3)   # our vector env

``make_vec(id, num_envs, task=... or tasks=...)`` returns the same ``gymnasium.vector.VectorEnv``
over the Rust environments (real MuJoCo 3.17 for the MuJoCo families), stepped on worker threads.
It follows gymnasium 1.x's vector API: ``reset(seed=...)`` -> ``(obs, infos)``, ``step(actions)``
-> ``(obs, rewards, terminations, truncations, infos)``, autoreset in gymnasium's default
``NEXT_STEP`` mode (the step after an episode ends resets that environment and ignores its action).

Seeds: ``reset(seed=s)`` gives environment i the seed ``s + i`` (gymnasium's convention);
``reset(seed=[s0, s1, ...])`` gives each its own (the seeds ``Policy.eval_plan`` lists, for
instance). Later automatic resets draw their seeds from a generator seeded at the last
``reset(seed=...)``, so a rollout is fully determined by its seeds and actions. The single env's
``reset(seed=s)`` is the vector env's environment 0 with seed ``s``.
"""
from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

from . import _native
from .errors import ArgumentTypeError, InvalidInputError, StateError
from ._args import _uint

try:
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode, VectorEnv
except ImportError as e:  # pragma: no cover - exercised only without gymnasium
    raise ImportError(
        "promptdt.envs needs gymnasium >= 1.0 (pip install gymnasium); the native "
        "promptdt._native.VecEnv works without it"
    ) from e

Obs = npt.NDArray[np.float32]
Bools = npt.NDArray[np.bool_]

#: The gymnasium namespace of promptdt's families.
NAMESPACE = "promptdt"


def families() -> Dict[str, Dict[str, Any]]:
    """Every family's tasks, dims, horizon and splits."""
    return _native.families()


def env_id(family: str) -> str:
    """The gymnasium id of a family: ``cheetah_vel`` -> ``promptdt/CheetahVel-v0``."""
    return f"{NAMESPACE}/{''.join(p.capitalize() for p in family.split('_'))}-v0"


#: gymnasium id -> family, for every family (``promptdt/CheetahVel-v0`` -> ``cheetah_vel``).
ENV_IDS: Dict[str, str] = {env_id(f): f for f in _native.families()}


class EnvClosedError(gym.error.ClosedEnvironmentError, InvalidInputError):
    """``reset`` or ``step`` after ``close()``: gymnasium's error, and a ``promptdt.InvalidInputError``
    (so a ``ValueError``)."""


def _seed(name: str, value: Any) -> int:
    return _uint(name, value, "a seed", high=2**64)


def _family_of(id: str) -> str:
    """A family name from a family name or a registered id (``promptdt/CheetahVel-v0``)."""
    if not isinstance(id, str):
        raise ArgumentTypeError(f"id: {id!r} ({type(id).__name__}) given, expected a family name or id")
    return ENV_IDS.get(id, id)


def _spaces(family: str, obs_dim: int, act_dim: int) -> Tuple[gym.spaces.Box, gym.spaces.Box]:
    # The family's action box, per dimension, from Rust (`EnvFamily::action_bounds`).
    fam = _native.families()[family]
    obs = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
    act = gym.spaces.Box(
        np.asarray(fam["action_low"], np.float32),
        np.asarray(fam["action_high"], np.float32),
        (act_dim,),
        np.float32,
    )
    return obs, act


def _metadata(base: Dict[str, Any], family: str) -> Dict[str, Any]:
    return {**base, "render_fps": _native.families()[family]["render_fps"]}


def _float_array(name: str, value: Any) -> npt.NDArray[np.float32]:
    """``value`` as float32, or a ``ValueError`` naming the argument (numpy's own message names
    neither it nor what was given)."""
    try:
        return np.asarray(value, dtype=np.float32)
    except (TypeError, ValueError) as e:
        given = repr(value)
        given = given if len(given) <= 80 else given[:77] + "..."
        raise InvalidInputError(
            f"{name}: {given} ({type(value).__name__}) given, expected an array of floats ({e})"
        ) from None


def _options(options: Optional[Dict[str, Any]]) -> Optional[Any]:
    """The task an ``options`` dict asks for (None: keep), refusing any other key: gymnasium
    passes options on, and one ignored silently would look honoured."""
    if options is None:
        return None
    if not isinstance(options, dict):
        raise ArgumentTypeError(f"options: {type(options).__name__} given, expected a dict or None")
    unknown = sorted(set(options) - {"task"})
    if unknown:
        raise InvalidInputError(
            f"options: unknown key(s) {unknown}; the only option is 'task' (a task index, or one "
            "per environment for a vector env)"
        )
    return options.get("task")


class PromptDTEnv(gym.Env[npt.NDArray[Any], npt.NDArray[Any]]):
    """One environment of a family, on one of its tasks: a plain ``gymnasium.Env``
    (``gymnasium.make("promptdt/CheetahVel-v0", task=3)``). ``reset(options={"task": t})``
    switches task."""

    metadata: Dict[str, Any] = {"render_modes": ["rgb_array"]}

    def __init__(
        self,
        family: str,
        task: int = 0,
        render_mode: Optional[str] = None,
        render_size: Tuple[int, int] = (480, 480),
    ):
        family = _family_of(family)
        task = _uint("task", task, "a task index")
        # Rendering (docs/rendering.md): checked before the environment is built.
        self.render_mode, self._render_size = _render_args(render_mode, render_size)
        self._env: Optional[_native.VecEnv] = _native.VecEnv(family, [task], 1)
        self.family: str = self._env.family
        self.metadata = _metadata(PromptDTEnv.metadata, self.family)
        self.task: int = task
        self.horizon: int = self._env.horizon
        self.observation_space, self.action_space = _spaces(
            self.family, self._env.obs_dim, self._env.act_dim
        )
        self._started = False

    def _native_env(self, call: str) -> _native.VecEnv:
        if self._env is None:
            raise EnvClosedError(f"{call}: this environment is closed (close() was called); make a new one")
        return self._env

    def reset(
        self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None
    ) -> Tuple[Obs, Dict[str, Any]]:
        """Starts an episode; returns ``(obs [obs_dim] float32, {"task", "seed"})``."""
        env = self._native_env("reset")
        if seed is not None:
            seed = _seed("seed", seed)
        task = _options(options)
        if task is not None:
            task = _uint("options['task']", task, "a task index")
            env = self._env = _native.VecEnv(self.family, [task], 1)
            self.task = task
        super().reset(seed=seed)
        # No seed: one drawn from the generator the last seed set (gymnasium's np_random).
        s = seed if seed is not None else int(self.np_random.integers(0, 2**63))
        obs = env.reset([s])[0]
        self._started = True
        return obs, {"task": self.task, "seed": s}

    def step(self, action: Any) -> Tuple[Obs, float, bool, bool, Dict[str, Any]]:
        """One step: ``(obs, reward, terminated, truncated, info)`` (``info["success"]`` for the
        families with a success criterion)."""
        env = self._native_env("step")
        if not self._started:
            raise StateError("call reset() before step()")
        a = _float_array("action", action)
        if a.shape != self.action_space.shape:
            raise InvalidInputError(f"action: shape {a.shape}, expected {self.action_space.shape} (act_dim,)")
        obs, rew, term, trunc = env.step(a[None])
        info: Dict[str, Any] = {}
        success = env.last_success()
        if success is not None:
            info["success"] = bool(success[0])
        return obs[0], float(rew[0]), bool(term[0]), bool(trunc[0]), info

    def render(self) -> Optional[npt.NDArray[np.uint8]]:
        """With ``render_mode="rgb_array"``: the current state as a ``[height, width, 3]`` uint8
        frame (``render_size`` is ``(width, height)``); without a render mode: None."""
        if self.render_mode is None:
            return None
        env = self._native_env("render")
        w, h = self._render_size
        return _native.render(env, 0, w, h)

    def close(self) -> None:
        self._env = None


class PromptDTVectorEnv(VectorEnv[Obs, Obs, npt.NDArray[Any]]):
    """Environments of one family, one per entry of ``tasks``, stepped together in Rust."""

    metadata: Dict[str, Any] = {
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": ["rgb_array"],
    }

    def __init__(
        self,
        family: str,
        tasks: Sequence[int],
        threads: int = 0,
        render_mode: Optional[str] = None,
        render_size: Tuple[int, int] = (480, 480),
    ):
        # Rendering (docs/rendering.md): checked before any environment is built.
        self.render_mode, self._render_size = _render_args(render_mode, render_size)
        self._threads = threads
        self._env: Optional[_native.VecEnv] = _native.VecEnv(_family_of(family), list(tasks), threads)
        self.family: str = self._env.family
        self.metadata = _metadata(PromptDTVectorEnv.metadata, self.family)
        self.tasks: List[int] = list(self._env.tasks)
        self.num_envs = self._env.num_envs
        self.horizon: int = self._env.horizon
        self._act_dim: int = self._env.act_dim
        self.single_observation_space, self.single_action_space = _spaces(
            self.family, self._env.obs_dim, self._act_dim
        )
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, self.num_envs
        )
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._started = False
        self._seed_rng = np.random.default_rng()

    def _native_env(self, call: str) -> _native.VecEnv:
        if self._env is None:
            raise EnvClosedError(f"{call}: this environment is closed (close() was called); make a new one")
        return self._env

    def _draw_seeds(self, n: int) -> List[int]:
        return [int(s) for s in self._seed_rng.integers(0, 2**63, size=n, dtype=np.int64)]

    def reset(
        self,
        *,
        seed: Optional[Union[int, Sequence[Optional[int]]]] = None,
        options: Optional[Dict[str, Any]] = None,
    ) -> Tuple[Obs, Dict[str, Any]]:
        """Resets every environment; returns ``(obs [num_envs, obs_dim], infos)``: ``infos["task"]``
        and ``infos["seed"]`` per environment, each with its ``_task``/``_seed`` mask (gymnasium's
        vector-info convention). ``options={"task": t}`` (one task, or one per environment) changes
        the tasks; any other option is refused."""
        env = self._native_env("reset")
        task = _options(options)
        if seed is None:
            seeds = self._draw_seeds(self.num_envs)
        elif isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            first = _seed("seed", seed)
            seeds = [_seed(f"seed + {i}", first + i) for i in range(self.num_envs)]
            self._seed_rng = np.random.default_rng(first)
        elif isinstance(seed, (list, tuple, np.ndarray)):
            given = list(seed)
            if len(given) != self.num_envs:
                raise InvalidInputError(
                    f"seed: {len(given)} seeds given, expected one per environment ({self.num_envs})"
                )
            drawn = self._draw_seeds(self.num_envs)
            seeds = [_seed(f"seed[{i}]", s) if s is not None else d for i, (s, d) in enumerate(zip(given, drawn))]
            self._seed_rng = np.random.default_rng([s % 2**63 for s in seeds])
        else:
            raise ArgumentTypeError(
                f"seed: {seed!r} ({type(seed).__name__}) given, expected an int, a list of one per "
                "environment, or None"
            )
        if task is not None:
            if isinstance(task, (list, tuple, np.ndarray)):
                tasks = [_uint(f"options['task'][{i}]", t, "a task index") for i, t in enumerate(task)]
                if len(tasks) != self.num_envs:
                    raise InvalidInputError(
                        f"options['task']: {len(tasks)} tasks given, expected one, or one per "
                        f"environment ({self.num_envs})"
                    )
            else:
                tasks = [_uint("options['task']", task, "a task index")] * self.num_envs
            env = self._env = _native.VecEnv(self.family, tasks, self._threads)
            self.tasks = list(env.tasks)
        obs = env.reset(seeds)
        self._autoreset[:] = False
        self._started = True
        every = np.ones(self.num_envs, dtype=bool)
        infos: Dict[str, Any] = {
            "task": np.asarray(self.tasks),
            "_task": every,
            "seed": np.asarray(seeds, dtype=np.uint64),
            "_seed": every.copy(),
        }
        return obs, infos

    def step(
        self, actions: Any
    ) -> Tuple[Obs, npt.NDArray[np.float64], Bools, Bools, Dict[str, Any]]:
        """Steps every environment with its row of ``actions`` ``[num_envs, act_dim]``; one that
        ended at the previous step is reset instead (its action ignored, reward 0)."""
        env = self._native_env("step")
        if not self._started:
            raise StateError("call reset() before step()")
        actions = _float_array("actions", actions)
        if actions.shape != (self.num_envs, self._act_dim):
            raise InvalidInputError(
                f"actions: shape {actions.shape}, expected "
                f"{(self.num_envs, self._act_dim)} (num_envs, act_dim)"
            )
        stepped = ~self._autoreset
        obs, rewards, term, trunc = env.step(actions, stepped.tolist())
        infos: Dict[str, Any] = {}
        success = env.last_success()
        if success is not None:
            # gymnasium's vector-info convention: the values, and `_success` marking the
            # environments that stepped (an environment being reset has no success value).
            infos["success"] = success
            infos["_success"] = stepped.copy()
        if self._autoreset.any():
            idx = np.flatnonzero(self._autoreset)
            first = env.reset(self._draw_seeds(len(idx)), idx.tolist())
            obs[idx] = first
        self._autoreset = term | trunc
        return obs, rewards.astype(np.float64), term, trunc, infos

    def render(self) -> Optional[Tuple[np.ndarray, ...]]:
        """With ``render_mode="rgb_array"``: each environment's current state as a
        ``[height, width, 3]`` uint8 frame (``render_size`` is ``(width, height)``), as
        ``SyncVectorEnv.render`` returns them; without a render mode: None."""
        if self.render_mode is None:
            return None
        env = self._native_env("render")
        w, h = self._render_size
        return tuple(_native.render(env, i, w, h) for i in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:
        self._env = None


def _render_args(
    render_mode: Optional[str], render_size: Any
) -> Tuple[Optional[str], Tuple[int, int]]:
    """``render_mode`` and ``render_size`` checked (rendering: docs/rendering.md)."""
    if render_mode not in (None, "rgb_array"):
        raise InvalidInputError(f"render_mode: {render_mode!r}, expected None or 'rgb_array'")
    try:
        w, h = (int(v) for v in render_size)
    except (TypeError, ValueError):
        raise InvalidInputError(f"render_size: {render_size!r}, expected (width, height)") from None
    if not (1 <= w <= 640 and 1 <= h <= 480):
        raise InvalidInputError(f"render_size: {(w, h)}, expected width 1..640 and height 1..480")
    return render_mode, (w, h)


def make_vec(
    id: str,
    num_envs: Optional[int] = None,
    *,
    task: Optional[int] = None,
    tasks: Optional[Sequence[int]] = None,
    threads: int = 0,
    render_mode: Optional[str] = None,
    render_size: Tuple[int, int] = (480, 480),
) -> PromptDTVectorEnv:
    """A gymnasium vector env of a family, in ``gymnasium.make_vec``'s argument order: ``id`` is a
    family (``families()``: ``point_robot``, ``cheetah_dir``, ``cheetah_vel``, ``ant_dir``,
    ``metaworld_reach``, ``dial``) or its gymnasium id (``promptdt/CheetahVel-v0``); ``num_envs``
    environments, all on ``task=t``, or on ``tasks=[...]`` (``num_envs`` then defaults to its
    length, or repeats it task by task: ``make_vec("cheetah_vel", 4, tasks=[2, 7])`` is tasks
    ``[2, 2, 7, 7]``). The task is a keyword, and required. ``threads``: worker threads stepping
    them (0: one per core). ``render_mode="rgb_array"``: ``render()`` returns each environment's
    frame, ``render_size`` = (width, height) pixels (docs/rendering.md)."""
    family = _family_of(id)
    if num_envs is not None and not isinstance(num_envs, (int, np.integer)):
        raise ArgumentTypeError(
            f"num_envs: {num_envs!r} ({type(num_envs).__name__}) given, expected a number of "
            "environments; the tasks go by keyword (make_vec(id, num_envs, task=t) or tasks=[...]), "
            "as in gymnasium.make_vec"
        )
    n = None if num_envs is None else _uint("num_envs", num_envs, "a number of environments", low=1)
    if (task is None) == (tasks is None):
        raise ArgumentTypeError(
            "make_vec: give the task by keyword, task=t or tasks=[...] (one of them): "
            f"make_vec({family!r}, num_envs={n or 1}, task=0). The second positional argument is "
            "num_envs, as in gymnasium.make_vec"
        )
    if task is not None:
        task_list = [_uint("task", task, "a task index")] * (n or 1)
    else:
        if isinstance(tasks, (str, bytes)) or not hasattr(tasks, "__iter__"):
            raise ArgumentTypeError(f"tasks: {tasks!r} given, expected a list of task indices")
        base = [_uint(f"tasks[{i}]", t, "a task index") for i, t in enumerate(tasks or [])]
        if not base:
            raise InvalidInputError("tasks: an empty list given, expected at least one task")
        if n is None or n == len(base):
            task_list = base
        elif n % len(base) == 0:
            task_list = [t for t in base for _ in range(n // len(base))]
        else:
            raise InvalidInputError(f"num_envs: {n} given, expected a multiple of the {len(base)} tasks given")
    return PromptDTVectorEnv(
        family, task_list, threads=threads, render_mode=render_mode, render_size=render_size
    )


def _vector_entry_point(
    num_envs: int = 1,
    *,
    family: str,
    task: Optional[int] = None,
    tasks: Optional[Sequence[int]] = None,
    threads: int = 0,
    render_mode: Optional[str] = None,
    render_size: Tuple[int, int] = (480, 480),
    max_episode_steps: Optional[int] = None,
) -> PromptDTVectorEnv:
    """``gymnasium.make_vec(id, num_envs=n, task=t)``: our vector env (task 0 when none is given,
    as ``gymnasium.make``). gymnasium passes the spec's ``max_episode_steps`` (the family's
    horizon, where the environments truncate); another limit is refused, not ignored."""
    horizon = _native.families()[family]["horizon"]
    if max_episode_steps is not None and max_episode_steps != horizon:
        raise InvalidInputError(
            f"max_episode_steps: {max_episode_steps!r} given; promptdt's vector env truncates at "
            f"{family}'s horizon ({horizon}). For another limit, vectorization_mode='sync' wraps "
            "each environment in gymnasium's TimeLimit"
        )
    if task is None and tasks is None:
        task = 0
    return make_vec(
        family,
        num_envs,
        task=task,
        tasks=tasks,
        threads=threads,
        render_mode=render_mode,
        render_size=render_size,
    )


def register_envs() -> None:
    """Registers every family with gymnasium (``ENV_IDS``); ``import promptdt`` calls it."""
    for gid, family in ENV_IDS.items():
        if gid in gym.registry:
            continue
        gym.register(
            id=gid,
            entry_point=f"{__name__}:PromptDTEnv",
            vector_entry_point=f"{__name__}:_vector_entry_point",
            kwargs={"family": family},
            # The family's horizon, where the environment truncates anyway: gymnasium.make's
            # TimeLimit then truncates at the same step, and the spec says the episode length
            # (what learners such as SB3 read from it).
            max_episode_steps=families()[family]["horizon"],
        )


__all__ = [
    "ENV_IDS",
    "EnvClosedError",
    "PromptDTEnv",
    "PromptDTVectorEnv",
    "env_id",
    "families",
    "make_vec",
    "register_envs",
]
