#!/usr/bin/env bash
# The README's two commands on a clean clone with nothing beside it, as a new user runs them.
#
#   bash scripts/check_fresh_clone.sh [REV] [DIR]
#
# Clones this checkout at REV (default HEAD: a branch, tag or commit; committed work only) into
# DIR/promptdt (default: a new temporary directory), so no ../shared lies beside the clone, then runs
# `make demo` and `make test` there. Prints the wall time of each and the test summary; exits non-zero
# when either fails. Nothing is reused from this checkout: the clone fetches libtorch and MuJoCo and
# builds everything cold (tens of minutes on 2 cores). Not part of .ci/run, which runs with the
# reference data beside the checkout; run it by hand before a release.
set -euo pipefail

src=$(cd "$(dirname "$0")/.." && pwd)
rev=${1:-HEAD}
base=${2:-$(mktemp -d "${TMPDIR:-/tmp}/promptdt-fresh.XXXXXX")}
clone="$base/promptdt"
commit=$(git -C "$src" rev-parse --verify "$rev^{commit}")

if [ -e "$clone" ]; then
    echo "$clone already exists: give an empty or new DIR" >&2
    exit 2
fi
if [ -e "$base/shared" ]; then
    echo "$base/shared exists: the clone must have nothing beside it" >&2
    exit 2
fi
mkdir -p "$base"
git clone --quiet --no-local "$src" "$clone"
git -C "$clone" checkout --quiet --detach "$commit"
echo "fresh clone of $commit at $clone"
cd "$clone"
# A user has none of these: no reference data, no required switches, no target dir from elsewhere.
unset PROMPTDT_REFERENCE_DATA PROMPTDT_REQUIRE_REFERENCE_DATA PROMPTDT_REQUIRE_LIVE_GOLDEN \
    PROMPTDT_LIVE_GOLDEN CARGO_TARGET_DIR

# Runs `make $1`, with its output in $base/make-$1.log and on the terminal; sets $secs and $rc.
run() {
    local start=$SECONDS
    set +e
    make "$1" 2>&1 | tee "$base/make-$1.log"
    rc=${PIPESTATUS[0]}
    set -e
    secs=$((SECONDS - start))
}
fmt() { printf '%d min %02d s' $(($1 / 60)) $(($1 % 60)); }

run demo
demo_rc=$rc demo_secs=$secs
test_rc=skipped test_secs=0
if [ "$demo_rc" = 0 ]; then
    run test
    test_rc=$rc test_secs=$secs
fi

echo
echo "== fresh clone of $commit ($clone) =="
echo "make demo: exit $demo_rc, $(fmt "$demo_secs")"
if [ "$test_rc" = skipped ]; then
    echo "make test: not run (make demo failed)"
else
    log="$base/make-test.log"
    passed=0 failed=0 ignored=0 binaries=0
    # One `test result:` line per test binary (doc tests included).
    while read -r p f i; do
        passed=$((passed + p)) failed=$((failed + f)) ignored=$((ignored + i)) binaries=$((binaries + 1))
    done < <(sed -n 's/.*test result: [A-Za-z]*\. \([0-9]*\) passed; \([0-9]*\) failed; \([0-9]*\) ignored.*/\1 \2 \3/p' "$log")
    echo "make test: exit $test_rc, $(fmt "$test_secs"): $passed passed, $failed failed, $ignored ignored in $binaries test binaries"
    sed -n '/^note: .* tests skipped what needs the reference/,$p' "$log"
    grep -E '^test .* FAILED$' "$log" | head -40 || true
fi
echo "logs: $base/make-demo.log, $base/make-test.log"
[ "$demo_rc" = 0 ] && [ "$test_rc" = 0 ]
