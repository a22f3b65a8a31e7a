#!/usr/bin/env bash
# Issue 30: a pack's MT-BC-Finetune runs holding libtorch's generator only while they fine-tune
# (b82ed82) against the build before (each held it for its whole evaluation). Each side is one whole
# process: a solo-engine pack (`train --pack`, the CPU's default engine) of three MT-BC-Finetune runs
# (seeds 0-2) and one Prompt-DT run (seed 1) on Cheetah-Dir, ITERATIONS iterations with a test
# evaluation after each (50 episodes per task, 10 fine-tuning steps of 256 before each test task).
# The two builds alternate ROUNDS times; every pack's run directories must equal the first pack's
# file for file (`metrics.*` but for their times and `run.json` aside), whatever the build.
#   OLD=path/to/promptdt-before NEW=target/release/promptdt DATA=path/to/data/cheetah_dir \
#     ROUNDS=2 bash scripts/bench/finetune_pack.sh
set -eu
OLD=${OLD:?set OLD to the promptdt binary of the build before}
NEW=${NEW:-target/release/promptdt}
DATA=${DATA:?set DATA to a Cheetah-Dir data directory (promptdt collect --env cheetah_dir ...)}
ITERATIONS=${ITERATIONS:-3}
ROUNDS=${ROUNDS:-2}
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
C=""
for spec in mt-bc-finetune:0 mt-bc-finetune:1 mt-bc-finetune:2 prompt-dt:1; do
  method=${spec%:*}
  seed=${spec#*:}
  f="$W/$method-$seed.toml"
  cat >"$f" <<TOML
[env]
name = "cheetah_dir"
[data]
dir = "$(realpath "$DATA")"
dataset_mode = "expert"
prompt_mode = "expert"
[run]
method = "$method"
seed = $seed
device = "cpu"
threads = 1
[train]
iterations = $ITERATIONS
test_eval_interval = 1
train_eval_interval = 0
TOML
  C="$C $f"
done
# The run directories without what differs by time alone.
fingerprint() {
  (cd "$1" && find . -type f ! -name 'metrics.*' ! -name run.json ! -name pack.json ! -name .lock \
    -exec sha256sum {} + | sort -k2)
}
first=""
differ=0
for r in $(seq "$ROUNDS"); do
  for side in OLD NEW; do
    bin=${!side}
    out="$W/$side-$r"
    t0=$(date +%s.%N)
    "$bin" train --quiet --pack $C --out "$out" >/dev/null
    t1=$(date +%s.%N)
    fingerprint "$out" >"$out.sums"
    if [ -z "$first" ]; then
      first="$out.sums"
      same="first"
    elif cmp -s "$first" "$out.sums"; then
      same="same as the first"
    else
      same="DIFFERENT from the first"
    fi
    awk -v s="$side" -v r="$r" -v a="$t0" -v b="$t1" -v m="$same" \
      'BEGIN { printf "round %d %s wall_s %.1f  run directories: %s\n", r, s, b - a, m }'
    if [ "$same" = "DIFFERENT from the first" ]; then
      diff "$first" "$out.sums" >&2 || true
      differ=1
    fi
  done
done
exit $differ
