"""The task family: gymnasium's classic-control Pendulum whose pole mass is the task.

This file is all the environment code a user writes: `make(task)` returns one task's
`gymnasium.Env`, `task` being the task's `params` table from `suite.toml` (`{"mass": 1.2}`). The
suite's `[environment]` names it (`entry = "tasks:make"`, `task_keyword = "task"`), so promptdt's
worker makes the evaluation episodes' environments with it; from Python the same function is the
factory of `promptdt.evaluate(run, env=...)`.
"""
import gymnasium as gym


def make(task):
    env = gym.make("Pendulum-v1")
    # PendulumEnv reads `m` at every step (its torque term is 3 / (m l^2) u): a heavier pole is
    # harder to swing up with the same torque limit, so the tasks need different policies.
    env.unwrapped.m = float(task["mass"])
    return env
