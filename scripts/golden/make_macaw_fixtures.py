#!/usr/bin/env python3
"""Write the PyTorch golden fixtures for the MACAW parity test (crates/macaw/tests/it/parity.rs).

    .venv/bin/python scripts/golden/make_macaw_fixtures.py [--out testdata/golden] [--threads 1]

One file per dtype, macaw_{f64,f32}.safetensors, made with the functional reference
scripts/golden/macaw_torch.py at tiny dims (obs 3, act 2, width 4; the latent of 100 and the head
of 32 are MACAW's own), and macaw_cpu.json (the CPU that made them). Contents:

  init.<param>, init.rho_v, init.rho_pi, init.rho_adv      starting point
  step{s}.task{k}.{inner,outer}.{obs,act,terminal_obs,terminal_discount,mc_return}   batches
  step{s}.task{k}.{value,policy}_{inner,outer}_loss         the four losses of each task
  step1.task{k}.adapted.<param>                             phi' and theta' of that task (step 1)
  step{s}.grad.<param>, step{s}.grad.rho_{v,pi,adv}         summed meta-gradients
  step{s}.after.<param>, step{s}.after.rho_{v,pi,adv}       after the Adam steps
  adapt.batch.*, adapt.probe_obs, adapt.<param>, adapt.mu   test-time adaptation (2 steps) from
                                                            the parameters after step 2

Two meta-steps (s = 1, 2), two tasks each, N_train = 3 (the official code divides by the number of
training tasks, not by the tasks of the step). Actions include negative components (the head's
ReLU-on-concat quirk) and kappa != 1. Adam: torch.optim.Adam(foreach=False), one per group, lrs
1e-5 (value), 1e-4 (policy), 1e-3 (rho_v, rho_pi, rho_adv).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import torch
from safetensors.torch import save_file

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import macaw_torch as mw  # noqa: E402
from make_prompt_dt_fixtures import cpu_fingerprint  # noqa: E402

OBS, ACT, WIDTH, B = 3, 2, 4, 8
N_TRAIN = 3
INIT_SEED = 7
INPUT_SEED = 20261124
ADAPT_B, ADAPT_STEPS = 6, 2


def batch(rng, n, dtype):
    """A batch as the official buffer would hold it: raw obs, actions in [-1, 1], s_T, kappa =
    gamma^(T-t) for some t, and Monte-Carlo returns of the size a cheetah sees."""
    steps_left = rng.integers(1, 200, size=(n, 1))
    b = {
        "obs": rng.standard_normal((n, OBS)) * 2.0,
        "act": np.clip(rng.standard_normal((n, ACT)), -1, 1),
        "terminal_obs": rng.standard_normal((n, OBS)) * 2.0,
        "terminal_discount": 0.99 ** steps_left,
        "mc_return": rng.standard_normal((n, 1)) * 30.0 + 50.0,
    }
    return {k: torch.tensor(v, dtype=dtype) for k, v in b.items()}


def make(dtype):
    torch.manual_seed(0)
    vdims, pdims = mw.layer_dims(OBS, ACT, WIDTH)
    vnames, pnames = mw.param_names("value", len(vdims)), mw.param_names("policy", len(pdims))
    gen = torch.Generator().manual_seed(INIT_SEED)
    vps = [p.requires_grad_() for p in mw.init_params(vdims, gen, dtype)]
    pps = [p.requires_grad_() for p in mw.init_params(pdims, gen, dtype)]
    rho_v = torch.full((len(vps),), float(np.log(1e-3)), dtype=dtype, requires_grad=True)
    rho_pi = torch.full((len(pps),), float(np.log(1e-3)), dtype=dtype, requires_grad=True)
    rho_adv = torch.tensor(float(np.log(0.01)), dtype=dtype, requires_grad=True)
    out = {}

    def put(prefix, names, tensors):
        for n, t in zip(names, tensors):
            out[f"{prefix}{n}"] = t.detach().clone()

    def put_rho(prefix):
        for n, t in (("rho_v", rho_v), ("rho_pi", rho_pi), ("rho_adv", rho_adv)):
            out[f"{prefix}{n}"] = t.detach().clone()

    put("init.", vnames + pnames, vps + pps)
    put_rho("init.")
    opts = [torch.optim.Adam(vps, lr=1e-5, foreach=False),
            torch.optim.Adam(pps, lr=1e-4, foreach=False),
            torch.optim.Adam([rho_v], lr=1e-3, foreach=False),
            torch.optim.Adam([rho_pi], lr=1e-3, foreach=False),
            torch.optim.Adam([rho_adv], lr=1e-3, foreach=False)]
    rng = np.random.default_rng(INPUT_SEED)
    for s in (1, 2):
        for o in opts:
            o.zero_grad(set_to_none=True)
        for k in (1, 2):
            d_in, d_out = batch(rng, B, dtype), batch(rng, B, dtype)
            for which, d in (("inner", d_in), ("outer", d_out)):
                for n, t in d.items():
                    out[f"step{s}.task{k}.{which}.{n}"] = t
            losses, v2, p2 = mw.meta_task(vps, pps, rho_v, rho_pi, rho_adv, vdims, pdims, d_in,
                                          d_out, N_TRAIN)
            for n, t in losses.items():
                out[f"step{s}.task{k}.{n}"] = t
            if s == 1:  # adapted parameters of the first step only (file size)
                put(f"step{s}.task{k}.adapted.", vnames + pnames, v2 + p2)
        grads = [p.grad for p in vps + pps]
        assert all(g is not None for g in grads)
        put(f"step{s}.grad.", vnames + pnames, grads)
        for n, t in (("rho_v", rho_v), ("rho_pi", rho_pi), ("rho_adv", rho_adv)):
            out[f"step{s}.grad.{n}"] = t.grad.detach().clone()
        for o in opts:
            o.step()
        put(f"step{s}.after.", vnames + pnames, vps + pps)
        put_rho(f"step{s}.after.")
    d = batch(rng, ADAPT_B, dtype)
    for n, t in d.items():
        out[f"adapt.batch.{n}"] = t
    probe = torch.tensor(rng.standard_normal((5, OBS)) * 2.0, dtype=dtype)
    out["adapt.probe_obs"] = probe
    v2, p2 = mw.adapt(vps, pps, rho_v, rho_pi, rho_adv, vdims, pdims, d, ADAPT_STEPS)
    put("adapt.", vnames + pnames, v2 + p2)
    out["adapt.mu"] = mw.policy_forward(p2, pdims, probe)[0].detach()
    return {k: v.contiguous() for k, v in out.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="testdata/golden")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    os.makedirs(args.out, exist_ok=True)
    meta = {"generator": f"scripts/golden/make_macaw_fixtures.py torch={torch.__version__} "
                         f"threads={args.threads} init_seed={INIT_SEED} input_seed={INPUT_SEED}"}
    for tag, dtype in (("f64", torch.float64), ("f32", torch.float32)):
        tensors = make(dtype)
        path = os.path.join(args.out, f"macaw_{tag}.safetensors")
        save_file(tensors, path, metadata=meta)
        print(f"{path}: {len(tensors)} tensors, {os.path.getsize(path)} bytes; losses step 1 task 1:",
              [float(tensors[f"step1.task1.{n}"]) for n in
               ("value_inner_loss", "value_outer_loss", "policy_inner_loss", "policy_outer_loss")],
              "grad rho_adv:", float(tensors["step1.grad.rho_adv"]))
    cpu = {"cpu": cpu_fingerprint(), "torch": torch.__version__,
           "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(), "threads": args.threads,
           "generator": meta["generator"]}
    path = os.path.join(args.out, "macaw_cpu.json")
    with open(path, "w") as fh:
        json.dump(cpu, fh, indent=1, sort_keys=True)
        fh.write("\n")
    print(f"{path}: {cpu['torch_cpu_capability']}")


if __name__ == "__main__":
    main()
