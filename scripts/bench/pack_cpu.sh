#!/usr/bin/env bash
# Issue 30 on the CPU: three Cheetah-Dir runs (Prompt-DT seeds 0 and 1, MT-ORL seed 0; the reference
# model, batch 2 x 16, K = 20) trained three ways, each timed as a whole process with farm-bench:
#   A  one batched pack in one process        (train --pack a b c)
#   B  three processes at once, sharing the cores
#   C  a solo-engine pack (the same three runs stepped one after another in one process)
# ITER iterations of 10 steps each, no evaluation until the last (1 episode per task), so the time is
# the training steps. Usage (from the repository root, a release build, Cheetah-Dir data at DATA):
#   DATA=path/to/data/cheetah_dir ITER=3 THREADS=1 bash scripts/bench/pack_cpu.sh
set -eu
BIN=${BIN:-target/release/promptdt}
DATA=${DATA:?set DATA to a Cheetah-Dir data directory (promptdt collect --env cheetah_dir ...)}
ITER=${ITER:-3}
THREADS=${THREADS:-1}
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
"$BIN" train --quiet --engine "\$1" --out "\$d/pack" --pack $C
rm -rf "\$d"
SH
echo "== A (batched pack) vs B (three processes at once)"
farm-bench -n ${N:-3} --timeout 3000 --vs "bash $W/three.sh" -- bash "$W/pack.sh" batched
echo "== A (batched pack) vs C (solo-engine pack)"
farm-bench -n ${N:-3} --timeout 3000 --vs "bash $W/pack.sh solo" -- bash "$W/pack.sh" batched
