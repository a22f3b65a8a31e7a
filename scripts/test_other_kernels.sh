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
#   bash scripts/test_other_kernels.sh --list     only print the test targets it would run
#
# Which tests: every integration test whose file (or a support file it includes by `#[path]`) names
# a place that holds committed numbers, or types a number with 6 or more decimals (the pattern
# below). The whole suite was run under these variables once (2026-12-06): no test outside this
# list compares with another machine's numbers (docs/reproducibility.md, "How the tests hold these
# claims on any CPU").
set -euo pipefail
cd "$(dirname "$0")/.."

# Places that hold numbers made on another machine.
# (Not `pretrained/`: a test that runs the committed agents is in the list only where it also names
# committed numbers to compare with, as reference_experts does; reproduce.rs, which only points
# sweeps at the agents and compares two sweeps made here, would add 12 minutes for nothing.)
pattern='testdata|golden|tests/fixtures|"results|/results|experiments/|reference::|shared/data|[0-9]\.[0-9]{6,}'

targets=()
for f in crates/*/tests/*.rs; do
    includes=$(sed -n 's/^#\[path = "\(.*\)"\]/\1/p' "$f" | sed "s|^|$(dirname "$f")/|")
    if grep -qE "$pattern" "$f" $includes 2>/dev/null; then
        targets+=("$(basename "$f" .rs)")
    fi
done
mapfile -t targets < <(printf '%s\n' "${targets[@]}" | sort -u)

if [[ "${1:-}" == "--list" ]]; then
    printf '%s\n' "${targets[@]}"
    exit 0
fi

args=()
for t in "${targets[@]}"; do args+=(--test "$t"); done
echo "test_other_kernels: ${#targets[@]} test targets under ATEN_CPU_CAPABILITY=default MKL_CBWR=COMPATIBLE ONEDNN_MAX_CPU_ISA=SSE41"
start=$(date +%s)
status=0
env -u PROMPTDT_LIVE_GOLDEN -u PROMPTDT_REQUIRE_LIVE_GOLDEN \
    ATEN_CPU_CAPABILITY=default MKL_CBWR=COMPATIBLE ONEDNN_MAX_CPU_ISA=SSE41 \
    OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}" \
    "${CARGO:-cargo}" test --release --workspace --no-fail-fast "${args[@]}" || status=$?
echo "test_other_kernels: exit $status in $(( $(date +%s) - start )) s"
exit $status
