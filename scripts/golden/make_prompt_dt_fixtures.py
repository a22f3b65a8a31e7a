#!/usr/bin/env python3
"""Write the PyTorch golden fixtures for the Rust parity test (crates/train/tests/it/parity.rs).

    .venv/bin/python scripts/golden/make_prompt_dt_fixtures.py [--out testdata/golden] [--threads 1]

Files (all safetensors; see testdata/golden/README.md for every name, shape and dtype):
  prompt_dt_state_dict.safetensors  model.state_dict() after torch.manual_seed(0) + construction
  prompt_dt_inputs.safetensors      one realistic batch (B=4, K=20) + prompt (Lp=5), cheetah dims 20/6
  prompt_dt_expected.safetensors    eval outputs (with / without prompt) and two training steps
  prompt_dt_cpu.json                the CPU and torch build that made them (the parity tests compare
                                    bit for bit only on a CPU with the same fingerprint)
  prompt_dt_bf16.safetensors        one training step under torch.autocast(cpu, bfloat16) from the same
                                    weights, batch and dropout seed (run.matmul = "bf16";
                                    crates/train/tests/it/parity_bf16.rs), and the fp32 step beside it

The batch imitates the reference's get_batch / get_prompt (reference (b.4), (b.5)): left padding,
states normalised after zero-padding, actions padded with -10, rtg / timesteps padded with 0.
Everything is drawn from numpy's PCG64 generator with seed INPUT_SEED, so the script is deterministic.
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
import prompt_dt_torch as pdt  # noqa: E402

STATE_DIM, ACT_DIM = 20, 6
B, K, LP = 4, 20, 5
INIT_SEED = 0  # torch.manual_seed before model construction
TRAIN_SEED = 1234  # torch.manual_seed right before the two training steps (dropout stream)
INPUT_SEED = 20240611  # numpy.random.default_rng seed for the inputs
HIST_TLEN = [20, 20, 7, 1]  # real steps per history row (pads = K - tlen, on the left)
PROMPT_TLEN = [5, 4, 5, 5]  # real steps per prompt row (row 1 has one pad step)
PROMPT_T0 = 194  # prompt = episode tail, steps 194..198 (T = 200, H = 5)
RTG_SCALE = 1000.0  # cheetah_dir


def segment(rng, tlen, seg_len, t0, state_mean, state_std, rtg0, reward_scale):
    """One left-padded segment like get_batch: returns s, a, r, rtg, timesteps, mask (numpy)."""
    pad = seg_len - tlen
    raw_s = (state_mean + state_std * rng.standard_normal((tlen, STATE_DIM))).astype(np.float32)
    a = np.tanh(rng.standard_normal((tlen, ACT_DIM))).astype(np.float32)  # in (-1, 1)
    r = (reward_scale * (1.0 + 0.2 * rng.standard_normal((tlen, 1)))).astype(np.float32)
    # rtg[j] = rtg0 - sum of earlier rewards / scale  (suffix sums, as discount_cumsum with gamma 1)
    rtg = (rtg0 - np.concatenate([[0.0], np.cumsum(r[:-1, 0])]) / RTG_SCALE).astype(np.float32)[:, None]
    ts = np.arange(t0, t0 + tlen, dtype=np.int64)

    s = np.concatenate([np.zeros((pad, STATE_DIM), np.float32), raw_s])
    s = ((s - state_mean) / state_std).astype(np.float32)  # normalised after padding: pads = -mean/std
    a = np.concatenate([np.full((pad, ACT_DIM), -10.0, np.float32), a])
    r = np.concatenate([np.zeros((pad, 1), np.float32), r])
    rtg = np.concatenate([np.zeros((pad, 1), np.float32), rtg])
    ts = np.concatenate([np.zeros(pad, np.int64), ts])
    mask = np.concatenate([np.zeros(pad, np.int64), np.ones(tlen, np.int64)])
    return s, a, r, rtg, ts, mask


def make_inputs():
    rng = np.random.default_rng(INPUT_SEED)
    state_mean = rng.normal(0.0, 1.0, STATE_DIM).astype(np.float32)
    state_std = rng.uniform(0.3, 3.0, STATE_DIM).astype(np.float32)
    hist, prompt = [], []
    for i in range(B):
        t0 = int(rng.integers(0, 980))  # si + K - 1 <= 998 < max_ep_len
        rtg0 = float(rng.uniform(0.7, 1.5))
        hist.append(segment(rng, HIST_TLEN[i], K, t0, state_mean, state_std, rtg0, reward_scale=5.0))
    for i in range(B):
        tlen = PROMPT_TLEN[i]
        t0 = PROMPT_T0 + (LP - tlen)
        # prompt rtg: return of the last ~6 steps of the episode / scale (small)
        prompt.append(segment(rng, tlen, LP, t0, state_mean, state_std, rtg0=0.035, reward_scale=5.0))
    names = ["states", "actions", "rewards", "returns_to_go", "timesteps", "attention_mask"]
    out = {}
    for j, n in enumerate(names):
        out[n] = torch.from_numpy(np.stack([h[j] for h in hist]))
        out["prompt_" + n] = torch.from_numpy(np.stack([p[j] for p in prompt]))
    return out


def batch_and_prompt(inp):
    names = ["states", "actions", "rewards", "returns_to_go", "timesteps", "attention_mask"]
    return tuple(inp[n] for n in names), tuple(inp["prompt_" + n] for n in names)


# The /proc/cpuinfo flags that change which kernels libtorch, MKL or oneDNN run, in this order.
# crates/testkit/src/cpu.rs (KERNEL_FLAGS) reads the same list the same way: change both together.
KERNEL_FLAGS = ["sse4_2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512dq", "avx512cd", "avx512bw",
                "avx512vl", "avx512_vnni", "avx512_bf16", "avx512_fp16", "avx512vbmi", "avx_vnni",
                "amx_tile", "amx_bf16", "amx_int8"]


def cpu_fingerprint():
    """Vendor, model name and kernel-relevant flags of the first processor in /proc/cpuinfo."""
    try:
        text = open("/proc/cpuinfo").read()
    except OSError:
        return None
    fields = {}
    for line in text.splitlines():
        k, sep, v = line.partition(":")
        if sep and k.strip() not in fields:
            fields[k.strip()] = v.strip()
    if "vendor_id" not in fields:
        return None
    have = set(fields.get("flags", "").split())
    return {"vendor_id": fields["vendor_id"], "model_name": fields.get("model name", ""),
            "isa": [f for f in KERNEL_FLAGS if f in have]}


def snapshot(d):
    """Detached, contiguous copies (a state_dict aliases the live parameters, which training changes)."""
    return {k: v.detach().clone(memory_format=torch.contiguous_format) for k, v in d.items()}


def bf16_step(state_dict, batch, prompt):
    """One training step as promptdt's `run.matmul = "bf16"` computes it: the forward pass inside
    torch.autocast(cpu, bfloat16), its action predictions cast to float32 before the loss (promptdt's
    one difference from plain autocast: the reference's loss is not on autocast's float32 list), the
    backward pass, clipping and AdamW outside, in float32 master weights. Beside it the float32 step
    from the same start and dropout seed, so the test can say how far bf16 is from fp32."""
    out = {}
    for tag, amp in (("bf16", True), ("fp32", False)):
        model = pdt.build_model(STATE_DIM, ACT_DIM)
        model.load_state_dict(state_dict)
        opt, sched = pdt.make_optimizer(model)
        model.train()
        torch.manual_seed(TRAIN_SEED)
        states, actions, rewards, rtg, timesteps, mask = batch
        with torch.autocast(device_type="cpu", dtype=torch.bfloat16, enabled=amp):
            _, action_preds, _ = model(states, actions, rewards, rtg, timesteps, mask, prompt=prompt)
        action_preds = action_preds.float()
        loss = pdt.masked_action_loss(action_preds, torch.clone(actions), mask)
        opt.zero_grad()
        loss.backward()
        for name, p in model.named_parameters():
            if p.grad is not None:
                out[f"{tag}.grad.{name}"] = p.grad.detach().clone()
        grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), pdt.GRAD_CLIP)
        opt.step()
        out[f"{tag}.action_preds"] = action_preds.detach()
        out[f"{tag}.loss"] = loss.detach()
        out[f"{tag}.grad_norm"] = grad_norm.detach()
        for name, p in model.named_parameters():
            out[f"{tag}.param.{name}"] = p.detach()
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "..", "..", "testdata", "golden"))
    ap.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    os.makedirs(args.out, exist_ok=True)

    torch.manual_seed(INIT_SEED)
    model = pdt.build_model(STATE_DIM, ACT_DIM)
    state_dict = snapshot(model.state_dict())
    inputs = make_inputs()
    batch, prompt = batch_and_prompt(inputs)
    expected = {}

    model.eval()
    with torch.no_grad():
        expected["eval.action_preds"] = model(*batch, prompt=prompt)[1]
        expected["eval_no_prompt.action_preds"] = model(*batch, prompt=None)[1]

    opt, sched = pdt.make_optimizer(model)
    assert pdt.adamw_uses_single_tensor_path(model), "expected AdamW's single-tensor path on CPU"
    model.train()
    torch.manual_seed(TRAIN_SEED)
    for k in (1, 2):
        grads = {} if k == 1 else None
        action_preds, loss, grad_norm, lr = pdt.train_step(model, opt, sched, batch, prompt, grads_out=grads)
        expected[f"train.{k}.action_preds"] = action_preds
        expected[f"train.{k}.loss"] = loss
        expected[f"train.{k}.grad_norm"] = grad_norm
        expected[f"train.lr.{k}"] = torch.tensor(lr, dtype=torch.float64)
        if grads is not None:
            for name, g in grads.items():
                expected[f"train.1.grad.{name}"] = g
    for name, p in model.named_parameters():
        expected[f"train.2.param.{name}"] = p

    # One metadata key only: safetensors writes a multi-key metadata map in hash order, which would make
    # the files differ from run to run.
    meta = {"generator": f"scripts/golden/make_prompt_dt_fixtures.py torch={torch.__version__} "
                         f"threads={args.threads} init_seed={INIT_SEED} train_seed={TRAIN_SEED} "
                         f"input_seed={INPUT_SEED}"}
    # Last, so that the fp32 fixtures above are what they were before it existed.
    bf16 = bf16_step(state_dict, batch, prompt)
    files = {
        "prompt_dt_bf16.safetensors": snapshot(bf16),
        "prompt_dt_state_dict.safetensors": state_dict,
        "prompt_dt_inputs.safetensors": snapshot(inputs),
        "prompt_dt_expected.safetensors": snapshot(expected),
    }
    for fname, tensors in files.items():
        path = os.path.join(args.out, fname)
        save_file(tensors, path, metadata=meta)
        print(f"{path}: {len(tensors)} tensors, {os.path.getsize(path)} bytes")
    cpu = {"cpu": cpu_fingerprint(), "torch": torch.__version__,
           "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(), "threads": args.threads,
           "generator": meta["generator"]}
    path = os.path.join(args.out, "prompt_dt_cpu.json")
    with open(path, "w") as fh:
        json.dump(cpu, fh, indent=1, sort_keys=True)
        fh.write("\n")
    print(f"{path}: {cpu['torch_cpu_capability']}, {cpu['cpu']}")
    no_grad = sorted(n for n, p in model.named_parameters() if f"train.1.grad.{n}" not in expected)
    print("parameters without a gradient:", no_grad)
    print("loss:", [float(expected[f"train.{k}.loss"]) for k in (1, 2)],
          "grad_norm:", [float(expected[f"train.{k}.grad_norm"]) for k in (1, 2)],
          "lr:", [float(expected[f"train.lr.{k}"]) for k in (1, 2)])


if __name__ == "__main__":
    main()
