"""Evaluates a run from Python in this process's own environments, `tasks.make`'s, and checks that
the returns equal those of `promptdt eval --run RUN` (its eval_final.json), which played the same
episodes in promptdt's worker process:

    python evaluate.py RUN
"""
import json
import pathlib
import sys

import promptdt
from tasks import make

run = pathlib.Path(sys.argv[1])
# The factory gets each task as the suite names it: {"index", "name", "params"}.
result = promptdt.evaluate(run, env=lambda task: make(task["params"]), progress=False)
cli = json.loads((run / "eval_final.json").read_text())
assert len(result["tasks"]) == len(cli["tasks"])
for ours, theirs in zip(result["tasks"], cli["tasks"]):
    assert ours["returns"] == theirs["returns"], (ours, theirs)
    print(f"{ours['task']}: returns {[round(r, 2) for r in ours['returns']]}, as promptdt eval's")
print(f"mean return {result['mean_return']:.2f}: equal to promptdt eval's, episode by episode")
