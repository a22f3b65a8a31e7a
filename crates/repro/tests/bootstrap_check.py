"""Independent check of the claim rule's bootstrap (crates/repro/src/stats.rs), run by
crates/repro/tests/bootstrap_python.rs.

Reads {"a": [[task scores of seed 1], ...], "b": [...]} on stdin and prints, as JSON, the exact
stratified-bootstrap distribution's 2.5 % and 97.5 % quantiles of mean(a) - mean(b): every way to
draw the seeds with replacement and, within each drawn seed, its tasks with replacement is
enumerated (all equally likely), so no random numbers are involved; the Rust side draws 10000 of
them from its own generator and must land close. Also the seeds' sample SD and the interquartile
mean of the pooled scores (scipy.stats.trim_mean(x, 0.25), written out with numpy).
"""
import itertools
import json
import sys

import numpy as np


def outcomes(cell):
    """Every equally likely bootstrap mean of one cell: seeds with replacement, then tasks."""
    n = len(cell)
    # Per seed, the mean of every ordered draw of its tasks with replacement.
    per_seed = [
        np.array([np.mean(d) for d in itertools.product(tasks, repeat=len(tasks))])
        for tasks in cell
    ]
    means = []
    for picks in itertools.product(range(n), repeat=n):
        # The drawn seeds' task means, every combination: their average.
        grids = np.meshgrid(*[per_seed[p] for p in picks], indexing="ij")
        means.append(sum(grids).ravel() / n)
    return np.concatenate(means)


def trim_mean(x, cut):
    x = np.sort(np.asarray(x, dtype=float))
    k = int(cut * len(x))
    return float(np.mean(x[k : len(x) - k]))


data = json.load(sys.stdin)
a, b = outcomes(data["a"]), outcomes(data["b"])
diff = np.subtract.outer(a, b).ravel()
lo, hi = np.quantile(diff, [0.025, 0.975])
out = {
    "diff_lo": float(lo),
    "diff_hi": float(hi),
    "a_lo": float(np.quantile(a, 0.025)),
    "a_hi": float(np.quantile(a, 0.975)),
    "a_sd": float(np.std([np.mean(t) for t in data["a"]], ddof=1)),
    "a_iqm": trim_mean([x for t in data["a"] for x in t], 0.25),
}
print(json.dumps(out))
