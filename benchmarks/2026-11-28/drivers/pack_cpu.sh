#!/usr/bin/env bash
# Issue 30 on the CPU: three Cheetah-Dir runs (Prompt-DT seeds 0 and 1, MT-ORL seed 0; the reference
# model, batch 2 x 16, K = 20) trained three ways, each timed as a whole process with farm-bench:
#   S  a solo-engine pack in one process      (train --engine solo --pack a b c: its runs' steps
#      one after another with THREADS libtorch threads, one copy of the data)
#   B  three processes at once, sharing the cores (each with THREADS libtorch threads)
#   A  a batched pack in one process          (train --engine batched --pack a b c)
# ITER iterations of 10 steps each, no evaluation until the last (1 episode per task), so the time is
# the training steps. Usage (from the repository root, a release build, Cheetah-Dir data at DATA):
#   DATA=path/to/data/cheetah_dir ITER=3 THREADS=1 bash scripts/bench/pack_cpu.sh
# BIN_OLD=path/to/promptdt adds C: that binary's solo-engine pack (another build's, to compare). OMP_WAIT_POLICY is passed on
# (PASSIVE unless set, as `reproduce` gives its runs). CASES picks the comparisons (default
# "SB AS", and SC with BIN_OLD), e.g. CASES=SB for the pack against three processes alone.
set -eu
BIN=${BIN:-target/release/promptdt}
DATA=${DATA:?set DATA to a Cheetah-Dir data directory (promptdt collect --env cheetah_dir ...)}
ITER=${ITER:-3}
THREADS=${THREADS:-1}
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-PASSIVE}
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
mk() { # method seed
  cat >"$W/$1-$2.toml" <<TOML
[env]
name = "cheetah_dir"
[data]
dir = "$(realpath "$DATA")"
[run]
method = "$1"
seed = $2
device = "cpu"
threads = $THREADS
[train]
iterations = $ITER
test_eval_interval = 1000
train_eval_interval = 0
save_interval = 1000
resume_interval = 1000
[eval]
episodes = 1
TOML
}
mk prompt-dt 0; mk prompt-dt 1; mk mt-orl 0
C="$W/prompt-dt-0.toml $W/prompt-dt-1.toml $W/mt-orl-0.toml"
cat >"$W/three.sh" <<SH
#!/usr/bin/env bash
d=\$(mktemp -d -p "$W")
for c in $C; do "$BIN" train --quiet --config "\$c" --out "\$d/\$(basename "\$c" .toml)" & done
wait
rm -rf "\$d"
SH
cat >"$W/pack.sh" <<SH
#!/usr/bin/env bash
d=\$(mktemp -d -p "$W")
"\${2:-$BIN}" train --quiet --engine "\$1" --out "\$d/pack" --pack $C
rm -rf "\$d"
SH
CASES=${CASES:-SB AS${BIN_OLD:+ SC}}
case " $CASES " in *" SB "*)
  echo "== S (solo-engine pack) vs B (three processes at once)"
  farm-bench -n ${N:-3} --timeout 3000 --vs "bash $W/three.sh" -- bash "$W/pack.sh" solo ;;
esac
case " $CASES " in *" AS "*)
  echo "== A (batched pack) vs S (solo-engine pack)"
  farm-bench -n ${N:-3} --timeout 3000 --vs "bash $W/pack.sh solo" -- bash "$W/pack.sh" batched ;;
esac
if [ -n "${BIN_OLD:-}" ] && [[ " $CASES " == *" SC "* ]]; then
  echo "== S (solo-engine pack) vs C (solo-engine pack of $BIN_OLD)"
  farm-bench -n ${N:-3} --timeout 3000 --vs "bash $W/pack.sh solo $(realpath "$BIN_OLD")" -- \
    bash "$W/pack.sh" solo
fi
