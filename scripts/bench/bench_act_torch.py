#!/usr/bin/env python3
"""PyTorch side of the `Policy.act` latency benchmark: the reference model's `get_action`.

    .venv/bin/python scripts/bench/bench_act_torch.py --batch 1 [--threads 1] [--steps 100] [--repeats 5]

The reference's per-step work for B episodes: grow each history by the new observation with
`torch.cat`, normalise, take the last K steps left-padded with zeros plus a 0/1 mask, one forward
of prompt + history under `torch.no_grad()`, the action at the last position handed out as
`.cpu().numpy()` (shared/reference/promptdt-reference.md (a.4), (d)). B = 1 is the reference's own
loop; B > 1 stacks the B histories into one forward (what the reference would do if it batched).
Model: scripts/golden/prompt_dt_torch.py (hidden 128, 3 layers, 1 head), point-robot dims (2, 2),
K = 20, a 5-step prompt (bench_eval_torch.make_prompt). Observations and rewards are synthetic (no
environment in the timed region). Prints one JSON line: mean milliseconds per call.
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

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "..", "golden"))
import prompt_dt_torch as pdt  # noqa: E402
from bench_eval_torch import ACT_DIM, RTG_SCALE, STATE_DIM, make_prompt  # noqa: E402


def episode(model, prompt, batch, steps, k, rng):
    """`steps` calls of a batched reference get_action; returns seconds per call."""
    obs = torch.from_numpy(rng.standard_normal((batch, 1, STATE_DIM)).astype(np.float32))
    states = obs
    actions = torch.zeros((batch, 0, ACT_DIM))
    rtg = torch.zeros((batch, 1, 1))
    timesteps = torch.zeros((batch, 1), dtype=torch.long)
    mean, std = torch.zeros(STATE_DIM), torch.ones(STATE_DIM)
    p = tuple(x.expand(batch, *x.shape[1:]) for x in prompt)
    t0 = time.perf_counter()
    for t in range(steps):
        actions = torch.cat([actions, torch.zeros((batch, 1, ACT_DIM))], dim=1)
        s = ((states - mean) / std)[:, -k:]
        a, r, ts = actions[:, -k:], rtg[:, -k:], timesteps[:, -k:]
        n, pad = s.shape[1], k - s.shape[1]
        mask = torch.cat([torch.zeros(pad), torch.ones(n)]).to(dtype=torch.long).reshape(1, -1).repeat(batch, 1)
        s = torch.cat([torch.zeros((batch, pad, STATE_DIM)), s], dim=1)
        a = torch.cat([torch.zeros((batch, pad, ACT_DIM)), a], dim=1)
        r = torch.cat([torch.zeros((batch, pad, 1)), r], dim=1)
        ts = torch.cat([torch.zeros((batch, pad), dtype=torch.long), ts], dim=1)
        _, preds, _ = model(s, a, None, r, ts, mask, prompt=p)
        act = preds[:, -1]
        actions[:, -1] = act
        act = act.detach().cpu().numpy()
        # the environment's answer (synthetic)
        new = torch.from_numpy(rng.standard_normal((batch, 1, STATE_DIM)).astype(np.float32))
        reward = torch.from_numpy(rng.standard_normal((batch, 1, 1)).astype(np.float32))
        states = torch.cat([states, new], dim=1)
        rtg = torch.cat([rtg, rtg[:, -1:] - reward / RTG_SCALE], dim=1)
        timesteps = torch.cat([timesteps, torch.full((batch, 1), t + 1, dtype=torch.long)], dim=1)
    return (time.perf_counter() - t0) / steps


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--steps", type=int, default=100, help="calls per timed episode")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--k", type=int, default=20)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = pdt.build_model(STATE_DIM, ACT_DIM)
    model.eval()
    prompt = make_prompt(2)
    rng = np.random.default_rng(0)
    with torch.no_grad():
        episode(model, prompt, args.batch, args.steps, args.k, rng)  # warm-up
        times = [episode(model, prompt, args.batch, args.steps, args.k, rng) for _ in range(args.repeats)]
    print(json.dumps({"engine": "pytorch get_action", "torch": torch.__version__, "batch": args.batch,
                      "threads": torch.get_num_threads(), "k": args.k, "steps": args.steps,
                      "ms_per_call": round(1e3 * statistics.median(times), 4),
                      "ms_per_call_all": [round(1e3 * x, 4) for x in times]}))


if __name__ == "__main__":
    main()
