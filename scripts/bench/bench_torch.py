#!/usr/bin/env python3
"""PyTorch side of the Prompt-DT speed benchmark (the Rust side runs the same four cases).

    .venv/bin/python scripts/bench/bench_torch.py [--threads N] [--iters 30] [--warmup 5] [--device cpu|cuda]

Model: scripts/golden/prompt_dt_torch.py (state 20, action 6, K 20, prompt length 5; 862,619 parameters).
Cases:
  train_b560  one full training step at batch 560 (cheetah_vel: 16 x 35 tasks): forward in train mode,
              masked MSE, zero_grad, backward, clip_grad_norm_(0.25), AdamW step, LambdaLR step
  train_b64   the same at batch 64
  train_b<N>_flat  the same as train_b<N> here (promptdt times its flat-buffer AdamW under this name)
  infer_b1    eval-mode forward under torch.no_grad() at batch 1 (one rollout step)
  infer_b50   the same at batch 50 (e.g. 50 parallel evaluation episodes)
Inputs are random but shaped like get_batch: left-padded histories (mask 0 = pad), prompt of 5 steps.
Each case: `--warmup` untimed iterations, then `--iters` timed ones; reports median, p10, p90 in ms.
On CUDA the device is synchronised before reading the clock at both ends of every iteration.
With --profile, also what one iteration runs, as promptdt's `bench --profile` counts it (torch's
profiler over 2 and 4 iterations after one warm-up, the difference over 2): host operators, CUDA
kernels, CUDA copies.
Prints one JSON object on stdout.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "golden"))
import prompt_dt_torch as pdt  # noqa: E402

STATE_DIM, ACT_DIM, K, PROMPT_LEN = 20, 6, 20, 5


def random_segment(gen, batch, length, device, full=False):
    """(states, actions, rewards, rtg, timesteps, mask), left-padded like get_batch."""
    tlen = torch.full((batch,), length) if full else torch.randint(1, length + 1, (batch,), generator=gen)
    tlen[0] = length  # at least one full row
    pos = torch.arange(length)
    mask = (pos[None, :] >= (length - tlen)[:, None]).long()
    real = mask.bool()[..., None]
    states = torch.where(real, torch.randn(batch, length, STATE_DIM, generator=gen), torch.tensor(-0.5))
    actions = torch.where(real, torch.rand(batch, length, ACT_DIM, generator=gen) * 2 - 1, torch.tensor(-10.0))
    rewards = torch.where(real, torch.randn(batch, length, 1, generator=gen), torch.tensor(0.0))
    rtg = torch.where(real, torch.rand(batch, length, 1, generator=gen) + 0.5, torch.tensor(0.0))
    start = torch.randint(0, 1000 - length, (batch, 1), generator=gen)
    timesteps = torch.where(mask.bool(), start + pos[None, :], torch.tensor(0))
    seg = (states, actions, rewards, rtg, timesteps, mask)
    return tuple(t.to(device) for t in seg)


def timed(fn, warmup, iters, sync):
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(iters):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - t0) * 1e3)
    times.sort()
    q = statistics.quantiles(times, n=10, method="inclusive") if len(times) > 1 else times * 9
    return {"median_ms": round(statistics.median(times), 4), "p10_ms": round(q[0], 4),
            "p90_ms": round(q[-1], 4), "iters": iters}


def profile_counts(step, device, sync):
    """One iteration's host operators, CUDA kernels and CUDA copies (see the module docs)."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])

    def counts(iters):
        with profile(activities=activities) as prof:
            for _ in range(1 + iters):
                step()
            sync()
        ops = kernels = copies = 0
        for e in prof.profiler.kineto_results.events():
            name = e.name()
            if e.device_type() == torch.autograd.DeviceType.CUDA:
                if name.startswith("Memcpy") or name.startswith("Memset"):
                    copies += 1
                else:
                    kernels += 1
            elif not name.startswith("cuda"):  # not a CUDA runtime or driver call
                ops += 1
        return ops, kernels, copies

    (a, b) = counts(2), counts(4)
    return {k: (y - x) / 2 for k, x, y in zip(("ops", "kernels", "copies"), a, b)}


class Autocast:
    """The model as promptdt's `run.matmul = "bf16"` runs it: each forward pass inside
    torch.autocast(bfloat16), the action predictions handed back in float32 (so the loss is float32,
    as promptdt's; crates/model/src/prompt_dt.rs, `forward`). Everything else is the model's."""

    def __init__(self, model, device_type):
        self.model, self.device_type = model, device_type

    def __call__(self, *args, **kwargs):
        with torch.autocast(device_type=self.device_type, dtype=torch.bfloat16):
            state_preds, action_preds, return_preds = self.model(*args, **kwargs)
        return state_preds, action_preds.float(), return_preds

    def __getattr__(self, name):
        return getattr(self.model, name)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    ap.add_argument("--iters", type=int, default=30)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--cases", default="train_b560,train_b64,infer_b1,infer_b50")
    # promptdt's --matmul: fp32 (PyTorch's default since 1.12), tf32 (cuBLAS on tensor cores) or
    # bf16 (the forward pass in torch.autocast(bfloat16), as promptdt's run.matmul = "bf16").
    ap.add_argument("--matmul", default="fp32", choices=["fp32", "tf32", "bf16"])
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args()
    # The legacy switch, as promptdt sets it (crates/torch/csrc/matmul.cpp): it keeps PyTorch's two
    # records of the setting in agreement. CUDA matmuls only.
    torch.backends.cuda.matmul.allow_tf32 = args.matmul == "tf32"

    load_before = os.getloadavg()[0]
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    gen = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    model = pdt.build_model(STATE_DIM, ACT_DIM).to(device)
    opt, sched = pdt.make_optimizer(model)
    if args.matmul == "bf16":
        model = Autocast(model, device.type)

    def train_case(batch):
        hist = random_segment(gen, batch, K, device)
        prompt = random_segment(gen, batch, PROMPT_LEN, device, full=True)

        def step():
            pdt.train_step(model, opt, sched, hist, prompt)
        return step, lambda: model.train()

    def infer_case(batch):
        hist = random_segment(gen, batch, K, device)
        prompt = random_segment(gen, batch, PROMPT_LEN, device, full=True)

        def step():
            with torch.no_grad():
                model(*hist, prompt=prompt)
        return step, lambda: model.eval()

    def make(name):
        # train_b<N> / infer_b<N>, any batch size N. train_b<N>_flat is promptdt's flat-buffer AdamW
        # (and, with _all, its last block on every token); PyTorch's side of both is the same
        # default AdamW step (foreach on CUDA), the reference's forward.
        kind, _, batch = name.removesuffix("_all").removesuffix("_flat").partition("_b")
        makers = {"train": train_case, "infer": infer_case}
        if kind not in makers or not batch.isdigit() or int(batch) < 1:
            raise SystemExit(f"unknown case {name!r} (train_b<N> or infer_b<N>)")
        return makers[kind](int(batch))

    results = []
    for name in args.cases.split(","):
        step, set_mode = make(name)
        set_mode()
        results.append({"name": name, **timed(step, args.warmup, args.iters, sync)})
        if args.profile:
            results[-1]["profile"] = profile_counts(step, device, sync)

    out = {"engine": "pytorch", "torch_version": torch.__version__, "threads": torch.get_num_threads(),
           "device": args.device, "results": results,
           # 1-minute load average before / after: other processes on a small machine skew the numbers
           "load_avg_1m": [round(load_before, 2), round(os.getloadavg()[0], 2)]}
    if device.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(device)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
