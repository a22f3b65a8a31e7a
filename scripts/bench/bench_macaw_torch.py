#!/usr/bin/env python3
"""PyTorch side of the MACAW meta-training speed benchmark (the Rust side is
`promptdt bench --cases macaw_w<W>_t<T>`, crates/macaw/src/bench.rs).

    .venv/bin/python scripts/bench/bench_macaw_torch.py [--threads N] [--iters 10] [--warmup 2] [--cases macaw_w100_t2,...]

One timed iteration = one meta-step of T tasks with batches of 256 (cheetah dims 20/6, width W):
zero the gradients; per task the value and policy inner steps with create_graph=True and the outer
backward passes; then the five Adams (torch.optim.Adam). The model is the functional reference
scripts/golden/macaw_torch.py (the parity tests' twin of crates/macaw), i.e. what MACAW's official
code computes with `higher`, without `higher`'s module patching overhead.
Prints one JSON object on stdout (median / p10 / p90 ms per meta-step).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "golden"))
import macaw_torch as mw  # noqa: E402

OBS, ACT, BATCH = 20, 6, 256


def parse_case(name):
    w, t = name.removeprefix("macaw_w").split("_t")
    return int(w), int(t)


def batch(device):
    return {
        "obs": torch.randn(BATCH, OBS, device=device) * 2.0,
        "act": torch.rand(BATCH, ACT, device=device) * 2.0 - 1.0,
        "terminal_obs": torch.randn(BATCH, OBS, device=device) * 2.0,
        "terminal_discount": torch.rand(BATCH, 1, device=device),
        "mc_return": torch.randn(BATCH, 1, device=device) * 30.0 + 50.0,
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--iters", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cases", default="macaw_w100_t2,macaw_w300_t2")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    results = []
    for case in args.cases.split(","):
        width, tasks = parse_case(case)
        vd, pd = mw.layer_dims(OBS, ACT, width)
        gen = torch.Generator().manual_seed(0)
        vps = [p.to(device).requires_grad_() for p in mw.init_params(vd, gen, torch.float32)]
        pps = [p.to(device).requires_grad_() for p in mw.init_params(pd, gen, torch.float32)]
        rho_v = torch.full((len(vps),), math.log(1e-3), device=device, requires_grad=True)
        rho_pi = torch.full((len(pps),), math.log(1e-3), device=device, requires_grad=True)
        rho_adv = torch.tensor(math.log(0.01), device=device, requires_grad=True)
        opts = [torch.optim.Adam(vps, lr=1e-5), torch.optim.Adam(pps, lr=1e-4),
                torch.optim.Adam([rho_v], lr=1e-3), torch.optim.Adam([rho_pi], lr=1e-3),
                torch.optim.Adam([rho_adv], lr=1e-3)]
        batches = [(batch(device), batch(device)) for _ in range(tasks)]

        def meta_step():
            for o in opts:
                o.zero_grad(set_to_none=True)
            for d_in, d_out in batches:
                mw.meta_task(vps, pps, rho_v, rho_pi, rho_adv, vd, pd, d_in, d_out, tasks)
            for o in opts:
                o.step()

        for _ in range(args.warmup):
            meta_step()
        times = []
        for _ in range(args.iters):
            sync()
            t0 = time.perf_counter()
            meta_step()
            sync()
            times.append((time.perf_counter() - t0) * 1e3)
        times.sort()
        q = lambda p: times[round((len(times) - 1) * p)]  # noqa: E731
        results.append({"name": case, "median_ms": statistics.median(times), "p10_ms": q(0.1),
                        "p90_ms": q(0.9), "iters": args.iters})
    print(json.dumps({"engine": "pytorch", "torch_version": torch.__version__,
                      "threads": torch.get_num_threads(), "results": results}))


if __name__ == "__main__":
    main()
