#!/usr/bin/env python3
"""Read a promptdt native trajectory file and print its per-episode returns.

The native format (docs/data-format.md) is a plain safetensors file, so nothing from promptdt is
needed to read it: `safetensors.numpy.load_file` gives the arrays, `safe_open(...).metadata()` the
string metadata. Steps of all episodes are concatenated; `episode_starts` ([E + 1] int64 offsets,
first 0, last N) delimits the episodes:

    from safetensors.numpy import load_file
    d = load_file("cheetah_vel-2-prompt-expert.safetensors")
    s = d["episode_starts"]
    for e in range(len(s) - 1):
        print(e, d["rewards"][s[e]:s[e + 1]].sum(dtype="float64"))

Usage: read_native_dataset.py FILE.safetensors

Output: one line of metadata, then one line per episode,
    episode <e> steps <T> return <R> terminated <0|1> truncated <0|1>
with R the float64 sum of the episode's float32 rewards (repr, so it round-trips), and the flags
those of the episode's last step.
"""

import sys

import numpy as np
from safetensors import safe_open
from safetensors.numpy import load_file


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    path = sys.argv[1]
    with safe_open(path, framework="np") as f:
        meta = f.metadata() or {}
    d = load_file(path)
    starts = d["episode_starts"]
    rewards = d["rewards"]
    print(
        "meta format={} version={} env={} task_index={} mode={} steps={} episodes={} "
        "obs_dim={} act_dim={}".format(
            meta.get("format"),
            meta.get("format_version"),
            meta.get("env"),
            meta.get("task_index"),
            meta.get("mode"),
            len(rewards),
            len(starts) - 1,
            d["observations"].shape[1],
            d["actions"].shape[1],
        )
    )
    for e in range(len(starts) - 1):
        s, t = int(starts[e]), int(starts[e + 1])
        ret = float(rewards[s:t].astype(np.float64).sum())
        print(
            f"episode {e} steps {t - s} return {ret!r} "
            f"terminated {int(d['terminated'][t - 1])} truncated {int(d['truncated'][t - 1])}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
