#!/usr/bin/env python3
"""PyTorch reference evaluation loop on point_robot, one episode at a time (to time against promptdt's
batched evaluation).

    .venv/bin/python scripts/bench/bench_eval_torch.py [--threads N] [--episodes 50] [--repeats 3] [--k 20] [--device cpu|cuda]

Follows shared/reference/promptdt-reference.md (d) `prompt_evaluate_episode_rtg` and (a.4) `get_action`:
model.eval() under torch.no_grad(), histories grown with torch.cat every step, the last K steps left-padded
with zeros plus a 0/1 mask, one batch-1 forward per environment step, the action taken from the last
position and handed to the environment as `.cpu().numpy()`. The same prompt is used for every episode of a
task. Environment: docs/point-robot.md (plain numpy, f32). Model: scripts/golden/prompt_dt_torch.py
(hidden 128, 3 layers, 1 head), state_dim 2, act_dim 2, random init with torch.manual_seed(0).
Protocol: test tasks [2, 10, 18, 26, 34] (split `default`), horizon 20, rtg_scale 10, target return 0,
state mean 0 / std 1, a fixed synthetic 5-step prompt per task (see `make_prompt`).
On `--device cuda` the model and every tensor of the loop live on the GPU, as in the reference's
`prompt_evaluate_episode_rtg(..., device=device)`; the action's `.cpu()` synchronises each step.
One untimed warm-up run of the whole protocol, then `--repeats` timed runs. Prints one JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "golden"))
import prompt_dt_torch as pdt  # noqa: E402

STATE_DIM, ACT_DIM = 2, 2
N_TASKS, HORIZON, MAX_SPEED = 40, 20, 0.1
TEST_TASKS = [2, 10, 18, 26, 34]
RTG_SCALE, TARGET_RETURN, PROMPT_LEN = 10.0, 0.0, 5
DEVICE = torch.device("cpu")  # set by --device


def goal_of(task: int) -> np.ndarray:
    angle = np.linspace(0.0, np.pi, N_TASKS)[task]  # computed in f64, rounded to f32
    return np.array([np.cos(angle), np.sin(angle)], dtype=np.float64).astype(np.float32)


class PointRobot:
    """docs/point-robot.md: state = position (f32), action = velocity clipped to [-0.1, 0.1] per coordinate,
    reward = -||pos - goal|| after the step, start at the origin, 20-step episodes (truncated at step 20)."""

    def __init__(self, task: int):
        self.goal = goal_of(task)
        self.reset()

    def reset(self) -> np.ndarray:
        self.pos = np.zeros(2, dtype=np.float32)
        self.t = 0
        return self.pos.copy()

    def step(self, action):
        action = np.asarray(action, dtype=np.float32).reshape(-1)
        if action.shape != (2,):
            raise ValueError(f"action of length {action.size}, expected 2")
        if not np.all(np.isfinite(action)):
            raise ValueError("non-finite action")
        if self.t >= HORIZON:
            raise RuntimeError("episode finished; call reset()")
        self.pos = (self.pos + np.clip(action, -MAX_SPEED, MAX_SPEED)).astype(np.float32)
        self.t += 1
        reward = -float(np.linalg.norm(self.pos - self.goal).astype(np.float32))
        return self.pos.copy(), reward, self.t >= HORIZON  # done = truncated (terminated is always false)


def make_prompt(task: int):
    """Synthetic 5-step prompt (batch 1): positions on the straight line to the goal at timesteps 14..18,
    actions 0.1 * direction, rewards = -distance after the step, rtg = remaining return / scale."""
    goal = goal_of(task).astype(np.float64)
    ts = np.arange(HORIZON - PROMPT_LEN - 1, HORIZON - 1)  # 14..18
    frac = lambda t: np.minimum(t / HORIZON, 1.0)  # noqa: E731
    states = goal[None, :] * frac(ts)[:, None]
    actions = np.repeat(MAX_SPEED * goal[None, :], PROMPT_LEN, axis=0)
    dist_after = 1.0 - frac(np.arange(HORIZON) + 1)
    rewards = -dist_after[ts]
    rtg = np.array([-dist_after[t:].sum() for t in ts]) / RTG_SCALE
    f = lambda a, *shape: torch.tensor(a, dtype=torch.float32, device=DEVICE).reshape(1, *shape)  # noqa: E731
    return (f(states, PROMPT_LEN, STATE_DIM), f(actions, PROMPT_LEN, ACT_DIM), f(rewards, PROMPT_LEN, 1),
            f(rtg, PROMPT_LEN, 1), torch.tensor(ts, dtype=torch.long, device=DEVICE).reshape(1, PROMPT_LEN),
            torch.ones(1, PROMPT_LEN, dtype=torch.long, device=DEVICE))


def get_action(model, states, actions, rewards, returns_to_go, timesteps, prompt, max_length):
    """Reference get_action (a.4): last K steps, left zero-padding, 0/1 mask, action at the last position."""
    states = states.reshape(1, -1, STATE_DIM)[:, -max_length:]
    actions = actions.reshape(1, -1, ACT_DIM)[:, -max_length:]
    returns_to_go = returns_to_go.reshape(1, -1, 1)[:, -max_length:]
    timesteps = timesteps.reshape(1, -1)[:, -max_length:]
    n, pad = states.shape[1], max_length - states.shape[1]
    d = DEVICE
    attention_mask = torch.cat([torch.zeros(pad, device=d), torch.ones(n, device=d)]).to(dtype=torch.long).reshape(1, -1)
    states = torch.cat([torch.zeros((1, pad, STATE_DIM), device=d), states], dim=1).to(dtype=torch.float32)
    actions = torch.cat([torch.zeros((1, pad, ACT_DIM), device=d), actions], dim=1).to(dtype=torch.float32)
    returns_to_go = torch.cat([torch.zeros((1, pad, 1), device=d), returns_to_go], dim=1).to(dtype=torch.float32)
    timesteps = torch.cat([torch.zeros((1, pad), dtype=torch.long, device=d), timesteps], dim=1).to(dtype=torch.long)
    _, action_preds, _ = model(states, actions, None, returns_to_go, timesteps, attention_mask, prompt=prompt)
    return action_preds[0, -1]


def evaluate_episode_rtg(env, model, prompt, state_mean, state_std, max_length):
    """Reference prompt_evaluate_episode_rtg (d), rtg mode `normal`. Returns (episode return, steps taken)."""
    d = DEVICE
    state = env.reset()
    states = torch.from_numpy(state).reshape(1, STATE_DIM).to(device=d, dtype=torch.float32)
    actions = torch.zeros((0, ACT_DIM), device=d, dtype=torch.float32)
    rewards = torch.zeros(0, device=d, dtype=torch.float32)
    target_return = torch.tensor(TARGET_RETURN / RTG_SCALE, device=d, dtype=torch.float32).reshape(1, 1)
    timesteps = torch.tensor(0, device=d, dtype=torch.long).reshape(1, 1)
    episode_return, length = 0.0, 0
    for t in range(HORIZON):
        actions = torch.cat([actions, torch.zeros((1, ACT_DIM), device=d)], dim=0)
        rewards = torch.cat([rewards, torch.zeros(1, device=d)])
        action = get_action(model, (states - state_mean) / state_std, actions, rewards, target_return,
                            timesteps, prompt, max_length)
        actions[-1] = action
        action = action.detach().cpu().numpy()
        state, reward, done = env.step(action)
        states = torch.cat([states, torch.from_numpy(state).to(device=d).reshape(1, STATE_DIM)], dim=0)
        rewards[-1] = reward
        pred_return = target_return[0, -1] - (reward / RTG_SCALE)
        target_return = torch.cat([target_return, pred_return.reshape(1, 1)], dim=1)
        timesteps = torch.cat([timesteps, torch.ones((1, 1), device=d, dtype=torch.long) * (t + 1)], dim=1)
        episode_return += reward
        length += 1
        if done:
            break
    return episode_return, length


def run_protocol(model, envs, prompts, episodes, k):
    """All test tasks, `episodes` each; returns (total env steps, per-episode returns)."""
    state_mean, state_std = torch.zeros(STATE_DIM, device=DEVICE), torch.ones(STATE_DIM, device=DEVICE)
    steps, returns = 0, []
    with torch.no_grad():
        for task in TEST_TASKS:
            for _ in range(episodes):
                ret, n = evaluate_episode_rtg(envs[task], model, prompts[task], state_mean, state_std, k)
                steps += n
                returns.append(ret)
    return steps, returns


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    ap.add_argument("--episodes", type=int, default=50, help="episodes per task")
    ap.add_argument("--repeats", type=int, default=3, help="timed full-protocol runs after 1 warm-up run")
    ap.add_argument("--k", type=int, default=20, help="history length K")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = ap.parse_args()
    global DEVICE
    DEVICE = torch.device(args.device)

    load_before = os.getloadavg()[0]
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = pdt.build_model(STATE_DIM, ACT_DIM).to(DEVICE)
    model.eval()
    envs = {t: PointRobot(t) for t in TEST_TASKS}  # constructed once per task and reused, like the reference
    prompts = {t: make_prompt(t) for t in TEST_TASKS}

    run_protocol(model, envs, prompts, args.episodes, args.k)  # warm-up
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        steps, returns = run_protocol(model, envs, prompts, args.episodes, args.k)
        times.append(time.perf_counter() - t0)
    q = statistics.quantiles(times, n=10, method="inclusive") if len(times) > 1 else times * 9
    median = statistics.median(times)
    out = {"engine": "pytorch-reference-loop", "torch_version": torch.__version__,
           "threads": torch.get_num_threads(), "episodes_per_task": args.episodes, "tasks": len(TEST_TASKS),
           "device": args.device, "k": args.k, "horizon": HORIZON, "repeats": args.repeats, "env_steps": steps,
           "median_s": round(median, 4), "p10_s": round(q[0], 4), "p90_s": round(q[-1], 4),
           "env_steps_per_s": round(steps / median, 1), "mean_return": round(float(np.mean(returns)), 4),
           # 1-minute load average before / after: other processes on a small machine skew the numbers
           "load_avg_1m": [round(load_before, 2), round(os.getloadavg()[0], 2)]}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
