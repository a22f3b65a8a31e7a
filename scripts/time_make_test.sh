#!/usr/bin/env bash
# `make test`'s build time and run time at several commits, on one machine under one load.
#
#   bash scripts/time_make_test.sh CLONE OUT.json REV [REV ...]
#
# CLONE is a clone of this repository whose target/ already holds the third-party crates (run
# `make test` there once, e.g. through scripts/check_fresh_clone.sh); its work tree is checked out
# at each REV in turn. For each REV the workspace's own crates and test binaries are removed from
# target/ (the third-party crates are kept: they are the same at every commit measured, so the
# comparison is of the workspace alone), then `cargo test --release --workspace --no-run` is timed
# (the build) and `make test` after it (the run: the build is then up to date). Writes a benchmark
# record (benchmarks/README.md) to OUT.json; render it with `promptdt bench render`. Pause other
# work on the machine first: the numbers are wall-clock seconds.
set -euo pipefail
clone=$(cd "$1" && pwd); out=$2; shift 2
log=$(mktemp -d "${TMPDIR:-/tmp}/time-make-test.XXXXXX")
cd "$clone"
unset PROMPTDT_REFERENCE_DATA PROMPTDT_REQUIRE_REFERENCE_DATA PROMPTDT_LIVE_GOLDEN CARGO_TARGET_DIR
rows=()
for rev in "$@"; do
    git checkout --quiet --detach "$rev"
    commit=$(git rev-parse --short=7 HEAD)
    pkgs=$(cargo metadata --no-deps --format-version 1 |
        python3 -c 'import json,sys; print(" ".join(p["name"] for p in json.load(sys.stdin)["packages"]))')
    for p in $pkgs; do cargo clean --release -p "$p" >/dev/null 2>&1; done
    # Test binaries are named after their target, not their package: remove every executable left.
    find target/release/deps -maxdepth 1 -type f -executable ! -name '*.so' -delete
    start=$(date +%s.%N)
    cargo test --release --workspace --no-run >"$log/$commit.build" 2>&1
    build=$(echo "$(date +%s.%N) - $start" | bc)
    bins=$(grep -c 'Executable' "$log/$commit.build")
    its=$(cargo metadata --no-deps --format-version 1 | python3 -c 'import json,sys
print(sum("test" in t["kind"] for p in json.load(sys.stdin)["packages"] for t in p["targets"]))')
    start=$(date +%s.%N)
    make test >"$log/$commit.test" 2>&1 || { echo "make test failed at $rev: $log/$commit.test" >&2; exit 1; }
    run=$(echo "$(date +%s.%N) - $start" | bc)
    passed=$(grep '^test result:' "$log/$commit.test" | awk '{n += $4} END {print n}')
    echo "$commit: build ${build} s, $bins test executables, $its integration-test binaries, run ${run} s, $passed passed"
    rows+=("$commit $build $run $bins $its $passed")
done
python3 - "$out" "$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | xargs), $(nproc) cores" \
    "$(date -u +%F)" "${rows[@]}" <<'PY'
import json, sys
out, cpu, date, *rows = sys.argv[1:]
rows = [r.split() for r in rows]
names = ["build s", "run s", "test executables", "integration-test binaries", "tests passed"]
table = {"case": "measure", "columns": [r[0] for r in rows], "rows": [
    {"case": n, "values": [round(float(r[k + 1]), 1) if k < 2 else int(r[k + 1]) for r in rows]}
    for k, n in enumerate(names)]}
if len(rows) == 2:
    table["ratios"] = [{"label": f"{rows[0][0]} / {rows[1][0]}", "num": 0, "den": 1}]
rec = {"title": "make test: build and run time", "what": "", "commands": [], "machine": {"cpu": cpu},
       "date": date, "tables": [table]}
with open(out, "w") as f:
    json.dump(rec, f, indent=2)
    f.write("\n")
PY
