#!/usr/bin/env python3
"""Where a real run loop's time goes, from its runs' `metrics.csv` (a pack's run
loop against solo runs): per run, the intervals between consecutive iterations' elapsed times,
split into training iterations and those that held an evaluation (longer than EVAL_FACTOR times the
median), and the pack's throughput in runs' iterations per second against solo runs'.

Usage: loop_rates.py --group NAME=DIR [--group NAME=DIR ...] [--baseline NAME[,NAME...]] [--json OUT]
A group is the runs found under DIR (a pack: every run's metrics.csv; a solo run: one). The first
interval (start-up, the first evaluation) is left out. With --baseline, each group's throughput is
divided by the baseline's: one solo run's iterations per second times the group's run count (for
several baseline groups, the mean of their seconds per iteration: the same runs one after another).
"""
import argparse
import csv
import json
import statistics
import sys
from pathlib import Path

EVAL_FACTOR = 4.0


def run_intervals(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    t = [float(r["time/elapsed_s"]) for r in rows]
    return [b - a for a, b in zip(t[1:], t[2:])], len(rows), t[-1] if t else 0.0


def group_stats(name, root):
    files = sorted(Path(root).rglob("metrics.csv"))
    if not files:
        sys.exit(f"{name}: no metrics.csv under {root}")
    train, evals, gross, lines = [], [], [], []
    for f in files:
        iv, n, last = run_intervals(f)
        lines.append(n)
        if not iv:
            sys.exit(f"{f}: fewer than 3 iterations")
        med = statistics.median(iv)
        train += [d for d in iv if d <= EVAL_FACTOR * med]
        evals += [d for d in iv if d > EVAL_FACTOR * med]
        gross.append(last / n)
    return {
        "group": name,
        "runs": len(files),
        "iterations_per_run": lines[0],
        "train_s_per_iteration_median": statistics.median(train),
        "train_s_per_iteration_mean": statistics.fmean(train),
        "evaluation_intervals_per_run": len(evals) / len(files),
        "evaluation_interval_s_median": statistics.median(evals) if evals else 0.0,
        "window_s_per_iteration": statistics.fmean(gross),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--group", action="append", required=True, help="NAME=DIR")
    ap.add_argument("--baseline", help="NAME[,NAME...]: solo groups to divide by")
    ap.add_argument("--json")
    a = ap.parse_args()
    groups = []
    for g in a.group:
        name, _, root = g.partition("=")
        groups.append(group_stats(name, root))
    base = None
    if a.baseline:
        names = a.baseline.split(",")
        chosen = [g for g in groups if g["group"] in names]
        if len(chosen) != len(names):
            sys.exit(f"--baseline {a.baseline}: not every name is a --group")
        base = {k: statistics.fmean(g[k] for g in chosen)
                for k in ("train_s_per_iteration_median", "train_s_per_iteration_mean",
                          "window_s_per_iteration")}
    print("| group | runs | iterations per run | training s/iteration (median; mean) "
          "| evaluation intervals per run (median s) | window s/iteration "
          "| runs' iterations/s, training (mean) | runs' iterations/s, window "
          + ("| / baseline, training (median; mean) | / baseline, window |" if base else "|"))
    print("|---|---:|---:|---:|---:|---:|---:|---:|" + ("---:|---:|" if base else ""))
    for g in groups:
        tr = g["runs"] / g["train_s_per_iteration_mean"]
        wi = g["runs"] / g["window_s_per_iteration"]
        line = (f"| {g['group']} | {g['runs']} | {g['iterations_per_run']} "
                f"| {g['train_s_per_iteration_median']:.4f}; {g['train_s_per_iteration_mean']:.4f} "
                f"| {g['evaluation_intervals_per_run']:.1f} ({g['evaluation_interval_s_median']:.2f}) "
                f"| {g['window_s_per_iteration']:.4f} | {tr:.1f} | {wi:.1f} |")
        if base:
            rm = g["runs"] * base["train_s_per_iteration_median"] / g["train_s_per_iteration_median"]
            rt = g["runs"] * base["train_s_per_iteration_mean"] / g["train_s_per_iteration_mean"]
            rw = g["runs"] * base["window_s_per_iteration"] / g["window_s_per_iteration"]
            g.update(ratio_train_median=rm, ratio_train_mean=rt, ratio_window=rw)
            line += f" {rm:.2f}x; {rt:.2f}x | {rw:.2f}x |"
        print(line)
    if a.json:
        Path(a.json).write_text(json.dumps({"groups": groups, "baseline": a.baseline}, indent=1))


if __name__ == "__main__":
    main()
