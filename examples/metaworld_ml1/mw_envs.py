"""Meta-World ML1 goal variations as promptdt tasks: the environment factory the suites' ``[environment]``
tables name (``entry = "mw_envs:make"``), and what the collection script shares with it.

ML1 (Meta-World's one-environment meta-RL benchmark) gives each environment 50 training "tasks":
object and goal positions drawn by ``metaworld.ML1(env_name, seed)``. Task ``goal = i`` of a suite is
``ML1(env_name, seed=ml1_seed).train_tasks[i]``. Meta-World hides the goal from the observation
(its last 3 values are zeros, ``_partially_observable``), so a policy has to tell the goals apart from
its prompt: the few-shot problem Prompt-DT is for.

Meta-World ignores ``reset(seed=...)`` (a task fixes its positions; ``SawyerXYZEnv.reset``), so
every episode of a task starts in the same state and promptdt's reset seeds change nothing here.
"""
from __future__ import annotations

import functools
from typing import Any, Dict

import metaworld
import numpy as np

#: Meta-World's episode length (``max_path_length``): the suites' ``max_ep_len``.
HORIZON = 500


@functools.lru_cache(maxsize=None)
def _ml1(env_name: str, ml1_seed: int) -> Any:
    # Building ML1 samples the 50 tasks of every goal (about 3 s); evaluation makes one environment
    # per episode, so the benchmark is made once per process.
    return metaworld.ML1(env_name, seed=ml1_seed)


def make(env_name: str, ml1_seed: int, task: Dict[str, Any]) -> Any:
    """The Meta-World environment of goal ``task["goal"]`` of ``ML1(env_name, seed=ml1_seed)``: a
    ``gymnasium.Env`` with 39 observations (goal zeroed) and 4 actions in [-1, 1]. ``task`` is the
    task's ``params`` table (the suite's ``task_keyword = "task"``)."""
    goal = int(task["goal"])
    ml1 = _ml1(env_name, int(ml1_seed))
    if not 0 <= goal < len(ml1.train_tasks):
        raise ValueError(f"goal {goal}: ML1 {env_name} has goals 0 to {len(ml1.train_tasks) - 1}")
    env = ml1.train_classes[env_name]()
    env.set_task(ml1.train_tasks[goal])
    return env


def policy_observation(env: Any, obs: np.ndarray) -> np.ndarray:
    """``obs`` with the goal the environment hides written back into its last 3 values: what
    Meta-World's scripted policies read (they were written for the goal-observable
    environments). Only the collection's policy sees it; the datasets keep ``obs``."""
    full = np.array(obs, dtype=np.float64, copy=True)
    full[-3:] = env._target_pos
    return full


def scripted_policy(env_name: str) -> Any:
    """Meta-World's own scripted policy for ``env_name`` (``metaworld.policies``)."""
    from metaworld import policies

    name = "Sawyer" + "".join(p.capitalize() for p in env_name.split("-")) + "Policy"
    # push-v3 -> SawyerPushV3Policy, pick-place-v3 -> SawyerPickPlaceV3Policy
    return getattr(policies, name)()
