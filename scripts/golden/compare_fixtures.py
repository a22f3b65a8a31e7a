#!/usr/bin/env python3
"""Measure how far two sets of golden fixtures (made on two CPUs) are apart.

    .venv/bin/python scripts/golden/compare_fixtures.py DIR_A DIR_B [--json OUT]

Both directories hold the files of `make_prompt_dt_fixtures.py`. Prints, per group of expected
tensors, the largest absolute difference, the largest difference relative to the tensor's own
largest magnitude (`max|a-b| / max|b|`), and how many values differ at all. These numbers are what
the tolerances of `crates/train/tests/it/parity.rs` (`CrossCpu`) are derived from: see
testdata/golden/README.md, "Across CPUs".

Needs numpy and safetensors only (no torch).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys

import numpy as np
from safetensors.numpy import load_file


def group(name: str) -> str:
    """Group expected tensors the way the parity test checks them."""
    if name.startswith("train.1.grad."):
        return "train.1.grad.*"
    if name.startswith("train.2.param."):
        return "train.2.param.*"
    return re.sub(r"^train\.[12]\.", "train.k.", name)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--json", help="also write the table as JSON here")
    args = ap.parse_args()

    for f in ("prompt_dt_state_dict.safetensors", "prompt_dt_inputs.safetensors"):
        x, y = load_file(os.path.join(args.a, f)), load_file(os.path.join(args.b, f))
        same = x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)
        print(f"{f}: {'identical' if same else 'DIFFERENT'}")

    a = load_file(os.path.join(args.a, "prompt_dt_expected.safetensors"))
    b = load_file(os.path.join(args.b, "prompt_dt_expected.safetensors"))
    if a.keys() != b.keys():
        print("expected tensors: different names", sorted(a.keys() ^ b.keys()), file=sys.stderr)
        return 1
    rows: dict[str, dict] = {}
    for name in sorted(a):
        x, y = a[name].astype(np.float64), b[name].astype(np.float64)
        d = np.abs(x - y)
        scale = float(np.abs(y).max()) if y.size else 0.0
        g = rows.setdefault(group(name), {"tensors": 0, "values": 0, "differing": 0,
                                          "max_abs": 0.0, "max_rel_to_max": 0.0})
        g["tensors"] += 1
        g["values"] += int(d.size)
        g["differing"] += int((d != 0).sum())
        g["max_abs"] = max(g["max_abs"], float(d.max()) if d.size else 0.0)
        if scale > 0:
            g["max_rel_to_max"] = max(g["max_rel_to_max"], float(d.max()) / scale)
    print(f"{'group':32} {'tensors':>7} {'differing values':>18} {'max |a-b|':>11} {'max|a-b|/max|b|':>16}")
    for k, g in rows.items():
        print(f"{k:32} {g['tensors']:7} {g['differing']:>8} of {g['values']:<7} {g['max_abs']:11.3e} "
              f"{g['max_rel_to_max']:16.3e}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
