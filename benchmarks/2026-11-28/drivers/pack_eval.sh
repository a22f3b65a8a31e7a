#!/usr/bin/env bash
# Issue 30: a batched pack's evaluations acting together (`--pack-eval together`: one batched
# forward of the pack's model per environment step for all runs evaluating) against apart (each run
# acting with its own solo model in its own thread, as before d44fa31). Each side is one whole
# process: a batched pack (`train --engine batched --pack ...`) of RUNS Cheetah-Dir runs
# (Prompt-DT and MT-ORL, seeds 0, 1, ...; the reference model, K = 20), one gradient step, then one
# evaluation on the 2 test tasks with EPISODES episodes each (200 steps), then its checkpoint; so the
# difference between the sides is the evaluation. Timed with farm-bench (N paired trials).
#   DATA=path/to/data/cheetah_dir RUNS=3 EPISODES=10 bash scripts/bench/pack_eval.sh
# DEVICE=cuda for a GPU (then THREADS libtorch threads per run, default 4; on the CPU 1).
set -eu
BIN=${BIN:-target/release/promptdt}
DATA=${DATA:?set DATA to a Cheetah-Dir data directory (promptdt collect --env cheetah_dir ...)}
RUNS=${RUNS:-3}
EPISODES=${EPISODES:-10}
DEVICE=${DEVICE:-cpu}
THREADS=${THREADS:-$([ "$DEVICE" = cpu ] && echo 1 || echo 4)}
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-PASSIVE}
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
C=""
for i in $(seq 0 $((RUNS - 1))); do
  method=$([ $((i % 2)) = 0 ] && echo prompt-dt || echo mt-orl)
  f="$W/run-$i.toml"
  cat >"$f" <<TOML
[env]
name = "cheetah_dir"
[data]
dir = "$(realpath "$DATA")"
[run]
method = "$method"
seed = $((i / 2))
device = "$DEVICE"
threads = $THREADS
[train]
iterations = 1
steps_per_iteration = 1
test_eval_interval = 1
train_eval_interval = 0
save_interval = 1
resume_interval = 1
[eval]
episodes = $EPISODES
TOML
  C="$C $f"
done
cat >"$W/pack.sh" <<SH
#!/usr/bin/env bash
d=\$(mktemp -d -p "$W")
"$(realpath "$BIN")" train --quiet --engine batched --pack-eval "\$1" --out "\$d/pack" --pack $C
rm -rf "\$d"
SH
echo "== A (evaluations acting together) vs B (apart: each run's own forwards), $RUNS runs on $DEVICE"
if command -v farm-bench >/dev/null; then
  farm-bench -n "${N:-3}" --timeout 3000 --vs "bash $W/pack.sh apart" -- bash "$W/pack.sh" together
else
  # (A machine without farm-bench, e.g. the device machine: the same pairs timed here, the
  # wall seconds of each side's process per trial, A B A B ...)
  bash "$W/pack.sh" together && bash "$W/pack.sh" apart # warm-up, not counted
  for i in $(seq "${N:-3}"); do
    for m in together apart; do
      t0=$(date +%s.%N); bash "$W/pack.sh" "$m"; t1=$(date +%s.%N)
      awk -v m="$m" -v i="$i" -v a="$t0" -v b="$t1" 'BEGIN { printf "trial %d %s wall_s %.3f\n", i, m, b - a }'
    done
  done
fi
