#!/usr/bin/env bash
# Issue 30's GPU measurements in one bounded call, then (optional) a family's cpu-budget cells as one
# pack for the results registry (issue 31). For a machine with an NVIDIA GPU and PyTorch 2.11 (CUDA
# 13); promptdt built anywhere (CPU-only link) takes libtorch's CUDA part from that PyTorch.
#   A. the training step against PyTorch (train_b64_flat, train_b560_flat);
#   B. pack cases (bench: packN_b32 with the flat pack optimiser and per-run masks, the old per-tensor
#      pack `_pt`, one solo run's step with the flat optimiser);
#   R. (R_ROUNDS=N) one solo run's step and the packs of 12 and 36, alternated N times in one process;
#   P. where a step's time goes: libtorch's profiler over one solo run's step (beside PyTorch's) and a
#      pack of 12's, at Cheetah-Dir's batch and Cheetah-Vel's (bench --profile: kernels per step,
#      the costliest);
#   T. TF32 against fp32 matmuls (--matmul, same call): the arithmetic-bound step (Cheetah-Vel's batch,
#      solo and a pack of 12) and the launch-bound one (pack12_b32), and a solo step with the last
#      block for the state tokens only against every token (train_b560_flat, _flat_all); the solo
#      step against PyTorch with TF32 too (T_S seconds; SKIP_T=1 skips it);
#   D. the real run loop at the paper budget, Cheetah-Dir (data in DATA/cheetah_dir): a pack of 12
#      (4 methods x 3 seeds), one solo run (or each of D_SOLO_CELLS in turn), a pack of 12 Prompt-DT
#      seeds (D_SEEDS_S > 0, `train --pack`), then the 12 runs as 12 processes at once; memory and
#      utilisation sampled by nvidia-smi every 0.5 s, each thread's CPU time in the packs;
#   E. FAMILY's cells of EXP at the cpu budget as one pack (collecting its data first), until the
#      deadline.
# Usage (repository root): BIN=... DATA=... OUT=... [DEADLINE=570] bash scripts/bench/gpu_pack.sh
# A rehearsal on a machine without a GPU (every phase's flags and the library path, before device time
# is spent on them): DEVICE=cpu PYTHON=.venv/bin/python with small case lists and short timings, e.g.
#   DEVICE=cpu PYTHON=.venv/bin/python D_MIN_S=9999 PACKS=pack3_b32,solo1_b32 \
#   P_CASES=train_b64_flat,pack3_b32 T_CASES=pack3_b32 ITERS=1 BIN=target/release/promptdt DATA=x OUT=o \
#   bash scripts/bench/gpu_pack.sh
set -u
start=$(date +%s)
BIN=${BIN:?}; OUT=${OUT:?}; DATA=${DATA:?}
PY=${PYTHON:-/opt/torch/.venv/bin/python}
DEADLINE=${DEADLINE:-570}
DEVICE=${DEVICE:-cuda}
# ITERS=1: one warm-up and one timed iteration per bench (a rehearsal's), instead of each phase's own.
its() { if [ -n "${ITERS:-}" ]; then echo "--iters $ITERS --warmup 1"; else echo "--iters $1 --warmup $2"; fi; }
WORK=${WORK:-/tmp/pdt-pack}
# At most 8 files come back from a device call: the samples and logs go to $WORK/o, packed at the end.
O=$WORK/o
mkdir -p "$OUT" "$WORK" "$O"
log() { echo "[$(($(date +%s) - start)) s] $*" | tee -a "$OUT/session.log"; }
left() { echo $((start + DEADLINE - $(date +%s))); }
. "$(dirname "$0")/gpu_env.sh"
# Without nvidia-smi (a CPU rehearsal) no samples are taken.
command -v nvidia-smi >/dev/null || nvidia-smi() { return 0; }
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee -a "$OUT/session.log"
(nproc; grep -m1 "model name" /proc/cpuinfo; sha256sum "$BIN"; cat "$BIN.commit" 2>/dev/null) | tee -a "$OUT/session.log"
smi() { # file: GPU utilisation and memory, and each process's memory, every 0.5 s
  nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader -lms 500 >"$1.gpu.csv" 2>/dev/null &
  echo $! >"$WORK/smi1"
  nvidia-smi --query-compute-apps=timestamp,pid,used_memory --format=csv,noheader -lms 500 >"$1.apps.csv" 2>/dev/null &
  echo $! >"$WORK/smi2"
}
smi_stop() { kill "$(cat "$WORK/smi1")" "$(cat "$WORK/smi2")" 2>/dev/null; }
bench() { # timeout out-name args...
  local t=$1 name=$2; shift 2
  timeout "$t" "$BIN" bench --device "$DEVICE" --threads 4 --out "$WORK/$name" "$@" >>"$OUT/session.log" 2>&1 || log "bench $name: rc $?"
  cp "$WORK/$name/bench.md" "$OUT/$name.md" 2>/dev/null
}

log "0. link check"
timeout 120 "$BIN" bench --device "$DEVICE" --cases infer_b1 --iters 3 --warmup 1 >>"$OUT/session.log" 2>&1 || { log "link check failed"; exit 1; }
PACKS=${PACKS:-solo1_b32,pack1_b32,pack3_b32,pack12_b32,pack36_b32,pack12_b32_pt,solo1_b32_pt}
if [ -z "${SKIP_A:-}" ]; then
  log "A. training step vs PyTorch"
  bench 90 bench_train --python "$PY" $(its 15 5) --cases train_b64_flat,train_b560_flat
fi
log "B. packs"; smi "$O/packs"
bench 120 bench_packs $(its 10 3) --cases "$PACKS"
smi_stop
# One call's cases can read differently by their place in it (the first one timed in a process ran
# 9.3 ms where the same case later ran 6.1 ms, 2026-11-27): the ratio is timed with the cases
# alternated, R_ROUNDS times each, in one process.
if [ -n "${R_ROUNDS:-}" ]; then
  log "R. solo and packs alternated, $R_ROUNDS rounds"
  R=""; for i in $(seq "$R_ROUNDS"); do R="$R,${R_CASES:-solo1_b32,pack12_b32,pack36_b32}"; done
  bench 120 bench_alt $(its 20 5) --cases "${R#,}"
fi
if [ -z "${SKIP_P:-}" ] && [ "$(left)" -gt ${P_S:-100} ]; then
  log "P. profile: kernels per step"
  bench ${P_S:-100} bench_profile $(its 3 2) --profile --python "$PY" \
    --cases "${P_CASES:-train_b64_flat,train_b560_flat,solo1_b32,pack12_b32,solo1_b560,pack12_b560}"
fi
if [ -z "${SKIP_T:-}" ] && [ "$(left)" -gt $((3 * ${T_S:-80})) ]; then
  T_CASES=${T_CASES:-solo1_b560,pack12_b560,pack12_b32,train_b560_flat,train_b560_flat_all}
  log "T. fp32 vs tf32 matmuls"
  bench ${T_S:-80} bench_fp32 $(its 8 3) --cases "$T_CASES"
  bench ${T_S:-80} bench_tf32 $(its 8 3) --cases "$T_CASES" --matmul tf32
  bench ${T_S:-80} bench_tf32_torch $(its 10 3) --cases train_b560_flat --python "$PY" --matmul tf32
fi
CELLS=""
for m in prompt-dt prompt-mt-bc mt-orl mt-bc-finetune; do for s in 0 1 2; do CELLS="$CELLS,cheetah_dir/$m/paper/seed$s"; done; done
CELLS=${CELLS#,}
runs_reached() { # dir: each run's first and last metrics line (iteration, elapsed s) into the log
  find "$1" -name metrics.csv | sort | while read -r f; do echo "$f $(sed -n 2p "$f" | cut -d, -f1,3) $(tail -1 "$f" | cut -d, -f1,3)"; done | tee -a "$OUT/session.log"
}
repro() { # timeout out-dir args...
  local t=$1 d=$2; shift 2
  timeout "$t" "$BIN" reproduce fig2 --budget paper --device "$DEVICE" --out "$WORK/$d" --data-root "$DATA" \
    --pretrained-root pretrained "$@" >"$O/$d.log" 2>&1; log "$d: rc $?"
  runs_reached "$WORK/$d"
}
# Each thread's CPU seconds (name, user, system ticks) in the newest promptdt process, twice
# THREADS_GAP_S apart, THREADS_AT_S after the start: which thread is busy (the pack's are named).
threads_cpu() {
  sleep "${THREADS_AT_S:-45}"; local pid; pid=$(pgrep -n -f "^$BIN ") || return 0
  for i in 1 2; do
    for t in /proc/"$pid"/task/*; do echo "$i $(date +%s.%N) ${t##*/} $(cut -d' ' -f2,14,15 "$t/stat" 2>/dev/null)"; done
    [ "$i" = 1 ] && sleep "${THREADS_GAP_S:-10}"
  done >"$O/$1.threads.txt"
}
if [ "$(left)" -gt ${D_MIN_S:-200} ]; then
  # A phase given 0 s is skipped.
  if [ "${D_PACK_S:-100}" -gt 0 ]; then
    log "D1. pack of 12, paper budget"; smi "$O/pk12"; threads_cpu pk12 &
    repro ${D_PACK_S:-100} pk12 --pack 12 --jobs 1 --threads 4 --only "$CELLS"; smi_stop; wait
  fi
  if [ "${D_SOLO_S:-45}" -gt 0 ]; then
    # D_SOLO_CELLS: the solo runs, one after another (e.g. one of each method of the pack).
    for cell in $(echo "${D_SOLO_CELLS:-cheetah_dir/prompt-dt/paper/seed0}" | tr , ' '); do
      d=solo1; [ -n "${D_SOLO_CELLS:-}" ] && d=solo-$(echo "$cell" | cut -d/ -f2)
      log "D2. one solo run: $cell"; smi "$O/$d"
      repro ${D_SOLO_S:-45} "$d" --pack 1 --jobs 1 --threads 4 --only "$cell"; smi_stop
    done
  fi
  if [ "${D_SEEDS_S:-0}" -gt 0 ]; then
    # A pack of 12 Prompt-DT runs (seeds 0-11; `train --pack`): the same method as the solo run.
    log "D4. pack of 12 Prompt-DT seeds"; smi "$O/seeds12"; mkdir -p "$WORK/seedcfg"
    cfgs=""; for s in $(seq 0 11); do
      # reproduce's resume points (every 25 iterations) and libtorch threads (4), as in D1 and D2.
      { sed -e "s/^seed = 0$/seed = $s\nthreads = 4/" configs/cheetah_dir/prompt-dt.toml
        printf '\n[train]\nresume_interval = 25\n'; } >"$WORK/seedcfg/prompt-dt-seed$s.toml"
      cfgs="$cfgs $WORK/seedcfg/prompt-dt-seed$s.toml"
    done
    threads_cpu seeds12 &
    timeout "$D_SEEDS_S" "$BIN" train --pack $cfgs --device "$DEVICE" --data "$DATA/cheetah_dir" --out "$WORK/seeds12" \
      --quiet >"$O/seeds12.log" 2>&1; log "seeds12: rc $?"; smi_stop; wait
    runs_reached "$WORK/seeds12"
  fi
  if [ "${D_PROC_S:-60}" -gt 0 ]; then
    log "D3. 12 processes at once"; smi "$O/proc12"
    repro ${D_PROC_S:-60} proc12 --pack 1 --jobs 12 --threads 1 --only "$CELLS"; smi_stop
  fi
fi
(cd "$WORK" && find pk12 solo* proc12 seeds12 -name metrics.csv -o -name 'run.json' -o -name pack.json 2>/dev/null | tar czf "$O/realloop.tar.gz" -T -)
if [ -n "${FAMILY:-}" ] && [ "$(left)" -gt 120 ]; then
  log "E. $FAMILY cpu-budget cells of ${EXP:-fig2}, one pack, $(left) s left"; smi "$O/fam"
  timeout $(( $(left) - 25 )) "$BIN" reproduce "${EXP:-fig2}" --budget cpu --device "$DEVICE" --out "$WORK/fam" --data-root "$WORK/famdata" \
    --pretrained-root pretrained --pack 12 --jobs 1 --threads 4 --only "$FAMILY_CELLS" >"$O/fam.log" 2>&1; log "E: rc $?"
  smi_stop
  (cd "$WORK" && find fam famdata -type f ! -name '*.safetensors' | tar czf "$OUT/fam_small.tar.gz" -T -)
fi
log "done"
(cd "$WORK" && tar czf "$OUT/samples.tar.gz" o)
ls -la "$OUT"
