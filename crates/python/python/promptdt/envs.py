"""promptdt's environment families as gymnasium vector environments.

``make_vec(family, tasks, num_envs)`` returns a ``gymnasium.vector.VectorEnv`` over the Rust
environments (real MuJoCo 3.17 for the MuJoCo families), stepped on worker threads. It follows
gymnasium 1.x's vector API: ``reset(seed=...)`` -> ``(obs, infos)``, ``step(actions)`` -> ``(obs,
rewards, terminations, truncations, infos)``, autoreset in gymnasium's default ``NEXT_STEP`` mode
(the step after an episode ends resets that environment and ignores its action).

Seeds: ``reset(seed=s)`` gives environment i the seed ``s + i`` (gymnasium's convention);
``reset(seed=[s0, s1, ...])`` gives each its own (the seeds ``Policy.eval_plan`` lists, for
instance). Later automatic resets draw their seeds from a generator seeded at the last
``reset(seed=...)``, so a rollout is fully determined by its seeds and actions.
"""
from __future__ import annotations

from typing import Any, List, Optional, Sequence, Tuple, Union

import numpy as np

from . import _native

try:
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode, VectorEnv
except ImportError as e:  # pragma: no cover - exercised only without gymnasium
    raise ImportError(
        "promptdt.envs needs gymnasium >= 1.0 (pip install gymnasium); the native "
        "promptdt._native.VecEnv works without it"
    ) from e

def families() -> dict:
    """Every family's tasks, dims, horizon and splits."""
    return _native.families()


class PromptDTVectorEnv(VectorEnv):
    """Environments of one family, one per entry of ``tasks``, stepped together in Rust."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"]}

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
        self._env = _native.VecEnv(family, [int(t) for t in tasks], threads)
        self.family = self._env.family
        self.tasks = list(self._env.tasks)
        self.num_envs = self._env.num_envs
        self.horizon = self._env.horizon
        # The family's action box, per dimension, from Rust (`EnvFamily::action_bounds`).
        fam = _native.families()[self.family]
        self.single_observation_space = gym.spaces.Box(
            -np.inf, np.inf, (self._env.obs_dim,), np.float32
        )
        self.single_action_space = gym.spaces.Box(
            np.asarray(fam["action_low"], np.float32),
            np.asarray(fam["action_high"], np.float32),
            (self._env.act_dim,),
            np.float32,
        )
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, self.num_envs
        )
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._started = False
        self._seed_rng = np.random.default_rng()

    def _draw_seeds(self, n: int) -> List[int]:
        return [int(s) for s in self._seed_rng.integers(0, 2**63, size=n, dtype=np.int64)]

    def reset(
        self,
        *,
        seed: Optional[Union[int, Sequence[Optional[int]]]] = None,
        options: Optional[dict] = None,
    ):
        """Resets every environment; returns ``(obs [num_envs, obs_dim], infos)``."""
        if seed is None:
            seeds = self._draw_seeds(self.num_envs)
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + i for i in range(self.num_envs)]
            self._seed_rng = np.random.default_rng(int(seed))
        else:
            seed = list(seed)
            if len(seed) != self.num_envs:
                raise ValueError(f"reset: {len(seed)} seeds for {self.num_envs} environments")
            drawn = self._draw_seeds(self.num_envs)
            seeds = [int(s) if s is not None else d for s, d in zip(seed, drawn)]
            self._seed_rng = np.random.default_rng([s % 2**63 for s in seeds])
        if any(s < 0 or s >= 2**64 for s in seeds):
            raise ValueError("reset: seeds must be in [0, 2**64)")
        obs = self._env.reset(seeds)
        self._autoreset[:] = False
        self._started = True
        return obs, {"task": np.asarray(self.tasks), "seed": np.asarray(seeds, dtype=np.uint64)}

    def step(self, actions: Any):
        """Steps every environment with its row of ``actions`` ``[num_envs, act_dim]``; one that
        ended at the previous step is reset instead (its action ignored, reward 0)."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        actions = np.asarray(actions, dtype=np.float32)
        if actions.shape != (self.num_envs, self.single_action_space.shape[0]):
            raise ValueError(
                f"actions: shape {actions.shape}, expected "
                f"{(self.num_envs, self.single_action_space.shape[0])} (num_envs, act_dim)"
            )
        stepped = ~self._autoreset
        obs, rewards, term, trunc = self._env.step(actions, stepped.tolist())
        infos: dict = {}
        success = self._env.last_success()
        if success is not None:
            # gymnasium's vector-info convention: the values, and `_success` marking the
            # environments that stepped (an environment being reset has no success value).
            infos["success"] = success
            infos["_success"] = stepped.copy()
        if self._autoreset.any():
            idx = np.flatnonzero(self._autoreset)
            first = self._env.reset(self._draw_seeds(len(idx)), idx.tolist())
            obs[idx] = first
        self._autoreset = term | trunc
        return obs, rewards.astype(np.float64), term, trunc, infos

    def render(self) -> Optional[Tuple[np.ndarray, ...]]:
        """With ``render_mode="rgb_array"``: each environment's current state as a
        ``[height, width, 3]`` uint8 frame (``render_size`` is ``(width, height)``), as
        ``SyncVectorEnv.render`` returns them; without a render mode: None."""
        if self.render_mode is None:
            return None
        if self._env is None:
            raise RuntimeError("render: the environment is closed")
        w, h = self._render_size
        return tuple(_native.render(self._env, i, w, h) for i in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:
        self._env = None


def _render_args(
    render_mode: Optional[str], render_size: Any
) -> Tuple[Optional[str], Tuple[int, int]]:
    """``render_mode`` and ``render_size`` checked (rendering: docs/rendering.md)."""
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"render_mode: {render_mode!r}, expected None or 'rgb_array'")
    try:
        w, h = (int(v) for v in render_size)
    except (TypeError, ValueError):
        raise ValueError(f"render_size: {render_size!r}, expected (width, height)") from None
    if not (1 <= w <= 640 and 1 <= h <= 480):
        raise ValueError(f"render_size: {(w, h)}, expected width 1..640 and height 1..480")
    return render_mode, (w, h)


def make_vec(
    family: str,
    tasks: Union[int, Sequence[int]],
    num_envs: Optional[int] = None,
    *,
    threads: int = 0,
    render_mode: Optional[str] = None,
    render_size: Tuple[int, int] = (480, 480),
) -> PromptDTVectorEnv:
    """A gymnasium vector env of ``family`` (``cheetah_vel``, ``cheetah_dir``, ``ant_dir``,
    ``point_robot``). ``tasks``: one task index for all ``num_envs`` environments, or one per
    environment (a list; ``num_envs`` then defaults to its length, or repeats it task by task:
    ``make_vec("cheetah_vel", [2, 7], num_envs=4)`` is tasks ``[2, 2, 7, 7]``). ``threads``: worker
    threads stepping them (0: one per core). ``render_mode="rgb_array"``: ``render()`` returns
    each environment's frame, ``render_size`` = (width, height) pixels."""
    if isinstance(tasks, (int, np.integer)):
        task_list = [int(tasks)] * (num_envs or 1)
    else:
        base = [int(t) for t in tasks]
        if not base:
            raise ValueError("tasks: give at least one task")
        if num_envs is None or num_envs == len(base):
            task_list = base
        elif num_envs % len(base) == 0:
            per = num_envs // len(base)
            task_list = [t for t in base for _ in range(per)]
        else:
            raise ValueError(
                f"num_envs {num_envs} is not a multiple of the {len(base)} tasks given"
            )
    return PromptDTVectorEnv(
        family, task_list, threads=threads, render_mode=render_mode, render_size=render_size
    )


__all__ = ["PromptDTVectorEnv", "families", "make_vec"]
