#!/usr/bin/env python3
"""PyTorch side of the SAC / TD3 update-speed benchmark (the Rust side is `promptdt bench --suite rl`).

    .venv/bin/python scripts/bench/bench_rl_torch.py [--threads N] [--iters 200] [--warmup 20] [--cases sac_h256_b256,...]

A plain PyTorch SAC and TD3 as in CleanRL's single-file implementations, at the sizes promptdt uses:
agent input 20 (HalfCheetah observation without the torso x, plus the task parameter), action 6,
hidden layers of H units, batch B. Separate `nn.Sequential` actor and twin critics, `torch.optim.Adam`.
One timed iteration = one update (SAC) or one policy-delay cycle of two updates (TD3) from a filled
replay buffer of 10,000 transitions (numpy arrays, indices from numpy, `torch.as_tensor` to the
device), exactly what promptdt's timed iteration does:
  sac: target with a fresh policy sample, twin-critic MSE, actor loss alpha*logp - min Q, temperature
       loss, Polyak update of the target critics (every step)
  td3: target-policy smoothing, twin-critic MSE; every 2nd update the actor (Q1) and both targets
Prints one JSON object on stdout (median / p10 / p90 ms per update).
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

OBS, ACT, BUFFER = 20, 6, 10_000


def mlp(i, hidden, o):
    layers, d = [], i
    for h in hidden:
        layers += [nn.Linear(d, h), nn.ReLU()]
        d = h
    layers.append(nn.Linear(d, o))
    return nn.Sequential(*layers)


class Buffer:
    def __init__(self, rng, device):
        self.obs = rng.standard_normal((BUFFER, OBS), dtype=np.float32)
        self.act = rng.uniform(-1, 1, (BUFFER, ACT)).astype(np.float32)
        self.rew = rng.standard_normal((BUFFER, 1), dtype=np.float32)
        self.next_obs = rng.standard_normal((BUFFER, OBS), dtype=np.float32)
        self.done = np.zeros((BUFFER, 1), dtype=np.float32)
        self.rng, self.device = rng, device

    def sample(self, b):
        i = self.rng.integers(0, BUFFER, b)
        t = lambda a: torch.as_tensor(a[i], device=self.device)  # noqa: E731
        return t(self.obs), t(self.act), t(self.rew), t(self.next_obs), t(self.done)


class Sac:
    def __init__(self, hidden, device):
        self.actor = mlp(OBS, hidden, 2 * ACT).to(device)
        self.qf1 = mlp(OBS + ACT, hidden, 1).to(device)
        self.qf2 = mlp(OBS + ACT, hidden, 1).to(device)
        self.qf1_t = mlp(OBS + ACT, hidden, 1).to(device)
        self.qf2_t = mlp(OBS + ACT, hidden, 1).to(device)
        self.qf1_t.load_state_dict(self.qf1.state_dict())
        self.qf2_t.load_state_dict(self.qf2.state_dict())
        self.q_opt = torch.optim.Adam(list(self.qf1.parameters()) + list(self.qf2.parameters()), lr=3e-4)
        self.a_opt = torch.optim.Adam(self.actor.parameters(), lr=3e-4)
        self.log_alpha = torch.zeros(1, requires_grad=True, device=device)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=3e-4)
        self.target_entropy = -float(ACT)

    def sample(self, obs):
        mean, log_std = self.actor(obs).chunk(2, dim=-1)
        log_std = log_std.clamp(-20, 2)
        std = log_std.exp()
        u = mean + std * torch.randn_like(mean)
        a = torch.tanh(u)
        logp = (-0.5 * ((u - mean) / std) ** 2 - log_std - 0.5 * math.log(2 * math.pi)).sum(-1, keepdim=True)
        logp = logp - (2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1, keepdim=True)
        return a, logp

    def update(self, b):
        obs, act, rew, next_obs, done = b
        alpha = self.log_alpha.exp().detach()
        with torch.no_grad():
            na, nlogp = self.sample(next_obs)
            x = torch.cat([next_obs, na], 1)
            q = torch.min(self.qf1_t(x), self.qf2_t(x)) - alpha * nlogp
            target = rew + (1 - done) * 0.99 * q
        x = torch.cat([obs, act], 1)
        q_loss = F.mse_loss(self.qf1(x), target) + F.mse_loss(self.qf2(x), target)
        self.q_opt.zero_grad()
        q_loss.backward()
        self.q_opt.step()
        a, logp = self.sample(obs)
        x = torch.cat([obs, a], 1)
        a_loss = (alpha * logp - torch.min(self.qf1(x), self.qf2(x))).mean()
        self.a_opt.zero_grad()
        a_loss.backward()
        self.a_opt.step()
        alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        self.alpha_opt.zero_grad()
        alpha_loss.backward()
        self.alpha_opt.step()
        with torch.no_grad():
            for net, tgt in ((self.qf1, self.qf1_t), (self.qf2, self.qf2_t)):
                for p, tp in zip(net.parameters(), tgt.parameters()):
                    tp.data.mul_(0.995).add_(0.005 * p.data)


class Td3:
    def __init__(self, hidden, device):
        self.actor = mlp(OBS, hidden, ACT).to(device)
        self.actor_t = mlp(OBS, hidden, ACT).to(device)
        self.actor_t.load_state_dict(self.actor.state_dict())
        self.qf1 = mlp(OBS + ACT, hidden, 1).to(device)
        self.qf2 = mlp(OBS + ACT, hidden, 1).to(device)
        self.qf1_t = mlp(OBS + ACT, hidden, 1).to(device)
        self.qf2_t = mlp(OBS + ACT, hidden, 1).to(device)
        self.qf1_t.load_state_dict(self.qf1.state_dict())
        self.qf2_t.load_state_dict(self.qf2.state_dict())
        self.q_opt = torch.optim.Adam(list(self.qf1.parameters()) + list(self.qf2.parameters()), lr=3e-4)
        self.a_opt = torch.optim.Adam(self.actor.parameters(), lr=3e-4)
        self.n = 0

    def update(self, b):
        obs, act, rew, next_obs, done = b
        with torch.no_grad():
            noise = (torch.randn_like(act) * 0.2).clamp(-0.5, 0.5)
            na = (torch.tanh(self.actor_t(next_obs)) + noise).clamp(-1, 1)
            x = torch.cat([next_obs, na], 1)
            target = rew + (1 - done) * 0.99 * torch.min(self.qf1_t(x), self.qf2_t(x))
        x = torch.cat([obs, act], 1)
        q_loss = F.mse_loss(self.qf1(x), target) + F.mse_loss(self.qf2(x), target)
        self.q_opt.zero_grad()
        q_loss.backward()
        self.q_opt.step()
        self.n += 1
        if self.n % 2 == 0:
            a_loss = -self.qf1(torch.cat([obs, torch.tanh(self.actor(obs))], 1)).mean()
            self.a_opt.zero_grad()
            a_loss.backward()
            self.a_opt.step()
            with torch.no_grad():
                for net, tgt in ((self.actor, self.actor_t), (self.qf1, self.qf1_t), (self.qf2, self.qf2_t)):
                    for p, tp in zip(net.parameters(), tgt.parameters()):
                        tp.data.mul_(0.995).add_(0.005 * p.data)


def parse_case(name):
    alg, h, b = name.split("_")
    assert alg in ("sac", "td3") and h.startswith("h") and b.startswith("b"), name
    return alg, int(h[1:]), int(b[1:])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cases", default="sac_h256_b256,sac_h128_b256,td3_h256_b256,td3_h128_b256")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    results = []
    for case in args.cases.split(","):
        alg, h, b = parse_case(case)
        agent = (Sac if alg == "sac" else Td3)([h, h], device)
        buf = Buffer(np.random.default_rng(0), device)
        per_iter = 1 if alg == "sac" else 2

        def iteration():
            for _ in range(per_iter):
                agent.update(buf.sample(b))

        for _ in range(args.warmup):
            iteration()
        times = []
        for _ in range(args.iters):
            sync()
            t0 = time.perf_counter()
            iteration()
            sync()
            times.append((time.perf_counter() - t0) * 1e3)
        times.sort()
        q = lambda p: times[round((len(times) - 1) * p)]  # noqa: E731
        results.append({"name": case, "median_ms": statistics.median(times), "p10_ms": q(0.1), "p90_ms": q(0.9), "iters": args.iters})
    print(json.dumps({"engine": "pytorch", "torch_version": torch.__version__, "threads": torch.get_num_threads(), "results": results}))


if __name__ == "__main__":
    main()
