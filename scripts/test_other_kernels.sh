#!/usr/bin/env bash
# Runs the tests that compare results with numbers committed from another machine (golden fixtures,
# committed run directories and results, the reference release's files, expected values in tests) a
# second time, under another code path in each of libtorch's kernel sources:
#
#   ATEN_CPU_CAPABILITY=default  ATen's unvectorised kernels (not AVX2 or AVX-512)
#   MKL_CBWR=COMPATIBLE          MKL's conditional-reproducibility branch for sgemm
#   ONEDNN_MAX_CPU_ISA=SSE41     oneDNN's SSE4.1 kernels
#
# (pdt_testkit::cpu::KERNEL_PATH_ENV; each changes the bits of some operation on an AVX2 CPU.) On
# such a path the floats differ in their last bits from any other machine's, as they would on a
# user's CPU of another vendor or width: a test that compares them bit for bit with committed
# numbers fails here, on the machine where it is written, instead of on a user's Intel AVX-512
# machine. The live PyTorch fixtures are left out (PROMPTDT_LIVE_GOLDEN unset): they
# were made on this machine's normal path, and these tests compare against the committed ones.
#
#   bash scripts/test_other_kernels.sh            (`make test-other-kernels`; CI runs it)
#   bash scripts/test_other_kernels.sh --list     only print the test modules it would run
#
# Which tests: every integration-test module (`crates/*/tests/it/NAME.rs`, a module of its crate's
# one test binary `it`, or a test binary of its own, `crates/*/tests/NAME.rs`) whose file, or a
# support file it uses (`use crate::NAME` of a module `tests/it/main.rs` declares, or one it
# includes by `#[path]`), names a place that holds committed numbers, or types a number with 6 or
# more decimals (the pattern below). The whole suite was run under these variables once (2026-12-06): no test outside this
# list compares with another machine's numbers (docs/reproducibility.md, "How the tests hold these
# claims on any CPU").
set -euo pipefail
cd "$(dirname "$0")/.."

# Places that hold numbers made on another machine.
# (Not `pretrained/`: a test that runs the committed agents is in the list only where it also names
# committed numbers to compare with, as reference_experts does; reproduce.rs, which only points
# sweeps at the agents and compares two sweeps made here, would add 12 minutes for nothing.)
pattern='testdata|golden|tests/fixtures|"results|/results|experiments/|reference::|shared/data|[0-9]\.[0-9]{6,}'

# The support files a module uses: `#[path = "P"] mod NAME;` in its crate's tests/it/main.rs, taken
# by `use crate::NAME` in the module, and `mod support;` (support/mod.rs), taken by `use crate::support`.
uses() {
    local f=$1 dir main name
    dir=$(dirname "$f")
    main=$dir/main.rs
    sed -n 's/^#\[path = "\(.*\)"\]/\1/p' "$f" | sed "s|^|$dir/|"
    [[ -f $main && $f != "$main" ]] || return 0
    for name in $(sed -n 's/^use crate::\([a-z_0-9]*\).*/\1/p' "$f"); do
        awk -v n="$name" -v d="$dir" '
            /^#\[path = "/ { split($0, q, "\""); p = q[2]; next }
            $0 == "mod " n ";" { print d "/" (p != "" ? p : n "/mod.rs"); exit }
            { p = "" }' "$main"
    done
}

modules=() # modules of the `it` binaries: run as `--test it -- NAME::`
binaries=() # test binaries of their own: `--test NAME`
for f in crates/*/tests/it/*.rs crates/*/tests/*.rs; do
    [[ $(basename "$f") == main.rs ]] && continue
    # shellcheck disable=SC2046 # one path a line, none with spaces
    if grep -qE "$pattern" "$f" $(uses "$f") 2>/dev/null; then
        if [[ $f == */tests/it/* ]]; then
            modules+=("$(basename "$f" .rs)")
        else
            binaries+=("$(basename "$f" .rs)")
        fi
    fi
done
mapfile -t modules < <(printf '%s\n' "${modules[@]}" | sed '/^$/d' | sort -u)
mapfile -t binaries < <(printf '%s\n' "${binaries[@]}" | sed '/^$/d' | sort -u)

if [[ "${1:-}" == "--list" ]]; then
    printf '%s\n' "${modules[@]}" "${binaries[@]}" | sed '/^$/d' | sort -u
    exit 0
fi

# A module named NAME is selected by the filter `NAME::` in every crate's `it` binary (as
# `--test NAME` selected every crate's test NAME before the tests were one binary a crate). A
# filter is a substring: `parity::` also matches `dial_parity::`, which must then be selected too.
for m in "${modules[@]}"; do
    for f in crates/*/tests/it/*"$m.rs"; do
        other=$(basename "$f" .rs)
        [[ -e $f && $other != "$m" ]] || continue
        printf '%s\n' "${modules[@]}" | grep -qx "$other" ||
            { echo "test_other_kernels: the filter $m:: would also run $f" >&2; exit 1; }
    done
done
filters=()
for m in "${modules[@]}"; do filters+=("$m::"); done
echo "test_other_kernels: ${#modules[@]} test modules and ${#binaries[@]} test binaries under ATEN_CPU_CAPABILITY=default MKL_CBWR=COMPATIBLE ONEDNN_MAX_CPU_ISA=SSE41"
start=$(date +%s)
status=0
kernels() {
    env -u PROMPTDT_LIVE_GOLDEN -u PROMPTDT_REQUIRE_LIVE_GOLDEN \
        ATEN_CPU_CAPABILITY=default MKL_CBWR=COMPATIBLE ONEDNN_MAX_CPU_ISA=SSE41 \
        OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}" "$@"
}
# --workspace in both: the features `make test` builds with, so nothing is built again.
if ((${#modules[@]})); then
    kernels "${CARGO:-cargo}" test --release --workspace --no-fail-fast --test it -- "${filters[@]}" ||
        status=$?
fi
if ((${#binaries[@]})); then
    args=()
    for t in "${binaries[@]}"; do args+=(--test "$t"); done
    kernels "${CARGO:-cargo}" test --release --workspace --no-fail-fast "${args[@]}" || status=$?
fi
echo "test_other_kernels: exit $status in $(( $(date +%s) - start )) s"
exit $status
