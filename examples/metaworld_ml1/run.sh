#!/usr/bin/env bash
# The Meta-World ML1 example end to end, from a clean clone (docs/your-own-tasks.md):
#
#   bash examples/metaworld_ml1/run.sh [OUT]        (default examples/metaworld_ml1/runs)
#
#   1. setup.sh: this example's virtual environment (metaworld from PyPI, the promptdt wheel);
#   2. collect.py: each suite's datasets and prompt sets, with Meta-World's scripted policies;
#   3. promptdt reproduce experiment.toml --seeds $SEEDS --budget $BUDGET --out OUT: trains and
#      evaluates (through promptdt's Python worker, in Meta-World) every cell and seed, then reports
#      (OUT/reports/metaworld_ml1-$BUDGET/report.md).
#
# Every step is resumable: run it again after a kill and it goes on where it stopped (setup is
# idempotent, collection skips the files it wrote, reproduce resumes its runs).
# Environment: SEEDS (default 3), BUDGET (cpu; smoke for a check in seconds per run), JOBS
# (reproduce's runs at once, default one per core), COLLECT_JOBS (default 2), PROMPTDT (the binary,
# default target/release/promptdt, built if missing).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
out="${1:-$here/runs}"
seeds="${SEEDS:-3}"
budget="${BUDGET:-cpu}"
promptdt="${PROMPTDT:-$root/target/release/promptdt}"

bash "$here/setup.sh"
if [ ! -x "$promptdt" ]; then
    (cd "$root" && cargo build --release -p promptdt)
fi
for env in push-v3 pick-place-v3; do
    "$here/.venv/bin/python" "$here/collect.py" "$here/$env.toml" "$here/data/$env" \
        --jobs "${COLLECT_JOBS:-2}"
done
jobs=()
if [ -n "${JOBS:-}" ]; then jobs=(--jobs "$JOBS"); fi
"$promptdt" reproduce "$here/experiment.toml" --budget "$budget" --seeds "$seeds" --out "$out" "${jobs[@]}"
echo "run.sh: report in $out/reports/metaworld_ml1-$budget/report.md"
