# Shared by the scripts/gpu/issue*_hold.sh scripts (sourced from the repository root): the run folder, a background
# job that outlives one device call, and waiting for it across calls.
export PYTHONPATH=/tmp/site:$PWD
R=/tmp/run; mkdir -p $R "$OUT"
background() { setsid nohup bash "$1" > $R/bg.log 2>&1 < /dev/null & echo $! > $R/bg.pid; }
# wait_bg S GLOB...: wait up to S seconds for the background job; its progress; the files matching GLOB to $OUT
wait_bg() {
  end=$((SECONDS + ${1:-500})); shift
  while kill -0 "$(cat $R/bg.pid)" 2>/dev/null && [ $SECONDS -lt $end ]; do sleep 5; done
  cat $R/steps.log; tail -c 800 $R/bg.log
  for f in "$@"; do [ -f "$f" ] && cp "$f" "$OUT"/; done
  ls "$OUT" | head -30
}
# unpack_wheels IMPORTS: the packed wheels (/tmp/gpu/part-*) into /tmp/site, the precompiled CUDA kernels into
# ~/.cache/warp, then an import check of IMPORTS (a python statement) and the GPU's state
unpack_wheels() {
  cat /tmp/gpu/part-* | xz -dc -T0 | tar x -C / || exit 1
  mkdir -p ~/.cache/warp && xz -dc scripts/gpu/kernel_cache/warp-1.19.0_newton-1.8.0_sm90.tar.xz | tar x -C ~/.cache/warp --skip-old-files
  python -c "$1" || exit 1
  nvidia-smi --query-gpu=name,memory.used --format=csv
}
# step TEXT: a timed line in the background job's progress log
step() { echo "$(date +%T) $*" >> $R/steps.log; }
# fresh_lift_data EPISODES ATTEMPTS SIM_MINUTES VAL TEST: lift_handle episodes simulated with Newton (WORLDS worlds per
# batch, default 64) and validated into /tmp/run/store.zarr (issue19_hold.sh data), VAL + TEST whole episodes held out
fresh_lift_data() {
  export TASKS="[lift_handle]" EPISODES=$1 ATTEMPTS=$2 SIM_MINUTES=$3 VAL_PER_TASK=$4 TEST_PER_TASK=$5 \
    WORLDS=${WORLDS:-64} WORKERS=1 TRAIN=0
  step "data start"
  bash scripts/gpu/issue19_hold.sh data > $R/data.log 2>&1
  step "data rc=$? $(tail -c 300 $R/data.log | tr '\r\n' '  ')"
}
