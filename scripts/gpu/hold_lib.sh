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
