#!/usr/bin/env bash
# The GPU checks of issue 12 in one bounded script, for a machine with an NVIDIA GPU and PyTorch 2.11
# (CUDA 13) in `python3`. It needs no network: promptdt (built on any x86-64 Linux machine, CPU-only
# link) takes the CUDA part of libtorch 2.11.0 from that PyTorch's own lib folder at run time.
#   1. link check: `promptdt bench --device cuda` on one case;
#   2. the bench next to PyTorch on the same GPU: training steps, inference, the evaluation protocol;
#   3. fig2 at the paper budget (5000 iterations x 10 steps), JOBS runs at once on the one GPU, in the
#      order of RUNS, until DEADLINE seconds after the start; then everything is packed into OUT.
#      Runs resume (`promptdt reproduce ... --only RUN` again, from the packed checkpoints).
# Usage (from the repository root):
#   BIN=path/to/promptdt OUT=dir [DATA=data-root] [DEADLINE=500] [JOBS=4] bash scripts/bench/gpu_session.sh
set -u
start=$(date +%s)
BIN=${BIN:-target/release/promptdt}
OUT=${OUT:?set OUT}
WORK=${WORK:-/tmp/pdt-gpu}
DATA=${DATA:-$WORK/data}
DEADLINE=${DEADLINE:-500}
JOBS=${JOBS:-4}
BUDGET=${BUDGET:-paper}  # smoke: a quick test of this script
DEVICE=${DEVICE:-cuda}  # cpu: likewise
PY=${PYTHON:-python3}
CELLS=${CELLS:-"cheetah_dir/prompt-dt/seed0 cheetah_dir/mt-orl/seed0 cheetah_vel/prompt-dt/seed0 cheetah_vel/mt-orl/seed0 cheetah_dir/prompt-mt-bc/seed0 cheetah_dir/mt-bc-finetune/seed0 cheetah_dir/prompt-dt/seed1 cheetah_dir/mt-orl/seed1"}
RUNS=$(for c in $CELLS; do echo "${c%/*}/$BUDGET/${c##*/}"; done)
mkdir -p "$OUT" "$WORK" "$DATA"
log() { echo "[$(($(date +%s) - start)) s] $*" | tee -a "$OUT/session.log"; }
left() { echo $((start + DEADLINE - $(date +%s))); }

. "$(dirname "$0")/gpu_env.sh"
log "torch lib: $TL"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee -a "$OUT/session.log"
nproc | sed 's/^/cores: /' | tee -a "$OUT/session.log"
(grep -m1 "model name" /proc/cpuinfo; sha256sum "$BIN"; cat "$BIN.commit" 2>/dev/null) | tee -a "$OUT/session.log"
ldd "$BIN" | grep -E 'torch|c10|cud|cupti|mujoco|gomp' | tee -a "$OUT/session.log"

log "1. link check"
if ! timeout 120 "$BIN" bench --device $DEVICE --cases infer_b1 --iters 3 --warmup 1 >>"$OUT/session.log" 2>&1; then
  log "link check failed"; exit 1
fi

if [ -z "${SKIP_BENCH:-}" ]; then
log "2. bench: model cases"
timeout 150 "$BIN" bench --device $DEVICE --threads 4 --python "$PY" --iters ${ITERS:-30} --warmup 5 \
  --cases train_b560,train_b64,train_b560_flat,train_b64_flat,infer_b1,infer_b50,act_b1,act_b50 --out "$WORK/bench_model" >>"$OUT/session.log" 2>&1 \
  || log "bench (model cases) failed: $?"
log "2. bench: evaluation protocol"
timeout 150 "$BIN" bench --device $DEVICE --threads 4 --python "$PY" --iters 3 --warmup 1 --eval-episodes ${EVAL_EPISODES:-50} \
  --cases eval_point_robot,eval_point_robot_full,eval_cheetah_vel,eval_cheetah_vel_full --out "$WORK/bench_eval" >>"$OUT/session.log" 2>&1 \
  || log "bench (evaluation) failed: $?"

cp "$WORK/bench_model/bench.md" "$OUT/bench_model.md"; cp "$WORK/bench_eval/bench.md" "$OUT/bench_eval.md"
fi
log "3. fig2 at the $BUDGET budget, $JOBS at once, $(left) s left"
mkdir -p "$WORK/repro/logs"
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader -l 15 >"$WORK/smi.csv" 2>/dev/null &
smi=$!
# Each run stops 45 s before the deadline (a run started late gets what is left); it resumes later.
export END=$((start + DEADLINE - 45)) BIN BUDGET DEVICE WORK DATA OUT EXP SEEDS
cat >"$WORK/job.sh" <<'JOB'
r=$1; t=$((END - $(date +%s)))
[ "$t" -gt 20 ] || { echo "$r not started (no time left)" >>"$OUT/session.log"; exit 0; }
timeout "$t" "$BIN" reproduce "${EXP:-fig2}" ${SEEDS:+--seeds "$SEEDS"} --budget "$BUDGET" --device "$DEVICE" --threads 2 --out "$WORK/repro" \
  --data-root "$DATA" --pretrained-root pretrained --only "$r" >"$WORK/repro/logs/$(echo "$r" | tr / _).gpu.log" 2>&1
echo "$r rc=$? after $(( $(date +%s) - END + t )) s" >>"$OUT/session.log"
JOB
for r in $RUNS; do echo "$r"; done | xargs -P "$JOBS" -n 1 bash "$WORK/job.sh" &
xr=$!
while kill -0 $xr 2>/dev/null; do
  for _ in 1 2 3; do sleep 10; kill -0 $xr 2>/dev/null || break; done
  for r in $RUNS; do
    f=$WORK/repro/runs/$r/checkpoints/latest.json
    [ -f "$f" ] && log "$r: iteration $(grep -o '"iteration": *[0-9]*' "$f" | grep -o '[0-9]*$')"
  done
done
kill $smi 2>/dev/null
log "4. report and packing"
timeout 30 "$BIN" reproduce "${EXP:-fig2}" --budget $BUDGET --out "$WORK/repro" --data-root "$DATA" --report-only >>"$OUT/session.log" 2>&1
# Small files of every run (curves, metrics, configs, logs), the report, and the datasets' summaries.
(cd "$WORK" && find repro data bench_model bench_eval smi.csv -type f ! -name '*.safetensors' | tar czf "$OUT/small.tar.gz" -T -)
# The latest resume point of the first CKPTS unfinished runs (default 4; model + optimizer state), one file each (16 MiB limit).
n=0
for r in $RUNS; do
  d=repro/runs/$r
  f=$WORK/$d/checkpoints/latest.json
  [ -f "$f" ] && [ $n -lt "${CKPTS:-4}" ] || continue
  # A finished run needs no resume point (its small files are in small.tar.gz).
  grep -q "^$r rc=0 " "$OUT/session.log" && continue
  m=$(grep -o '"model": *"[^"]*"' "$f" | sed 's/.*"\([^"]*\)"$/\1/')
  s=$(grep -o '"state": *"[^"]*"' "$f" | sed 's/.*"\([^"]*\)"$/\1/')
  (cd "$WORK" && tar cf "$OUT/ckpt-$(echo "$r" | tr / _).tar" "$d/checkpoints/$m" "$d/checkpoints/$s" 2>/dev/null)
  n=$((n + 1))
done
# Optional: bench cases after the runs (AFTER_CASES, within AFTER_S seconds), so that the runs get
# the device first and the timings an idle device.
if [ -n "${AFTER_CASES:-}" ]; then
  log "5. bench after the runs: $AFTER_CASES"
  timeout "${AFTER_S:-60}" "$BIN" bench --device $DEVICE --threads 4 ${AFTER_PYTHON:+--python "$PY"} --iters ${ITERS:-10} --warmup 3 \
    --cases "$AFTER_CASES" --out "$WORK/bench_after" >>"$OUT/session.log" 2>&1 || log "bench after the runs failed: $?"
  cp "$WORK/bench_after/bench.md" "$OUT/bench_after.md" 2>/dev/null
fi
log "done"
ls -la "$OUT"
