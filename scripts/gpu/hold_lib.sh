# What the recorded GPU runs in scripts/gpu/ share (sourced from the repository root): the run folder /tmp/run ($R),
# the reports folder $OUT (default /tmp/run/out), a background job that outlives one device call and waiting for it,
# the precompiled CUDA kernels and packed wheels put in place, a timed progress log, a model folder from a cut
# training, and the fresh lift_handle data and expand / teacher check / held-out rollout chain most runs start with.
# The recorded runs ran on machines without network access, their Python packages carried as packed wheels
# (/tmp/gpu/part-*, unpacked into /tmp/site, put on PYTHONPATH).
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
R=/tmp/run
export OUT=${OUT:-$R/out}
mkdir -p $R "$OUT"
KERNELS=${KERNELS:-scripts/gpu/kernel_cache/warp-1.19.0_newton-1.8.0_sm90.tar.xz}

# step TEXT: a timed line in the run's progress log ($R/steps.log)
step() { echo "$(date +%T) $*" >> $R/steps.log; }
# background SCRIPT: run SCRIPT detached (it outlives this call); its output in $R/bg.log
background() { setsid nohup bash "$1" > $R/bg.log 2>&1 < /dev/null & echo $! > $R/bg.pid; }
# wait_bg S GLOB...: wait up to S seconds for the background job; its progress; the files matching GLOB to $OUT
wait_bg() {
  end=$((SECONDS + ${1:-500})); shift
  while kill -0 "$(cat $R/bg.pid)" 2>/dev/null && [ $SECONDS -lt $end ]; do sleep 5; done
  cat $R/steps.log; tail -c 800 $R/bg.log
  for f in "$@"; do [ -f "$f" ] && cp "$f" "$OUT"/; done
  ls "$OUT" | head -30
}
# unpack_kernels: the precompiled CUDA kernels ($KERNELS, scripts/gpu/precompile_cuda_kernels.py) into ~/.cache/warp;
# without them the first simulate compiles for ~13 min
unpack_kernels() {
  if [ -f "$KERNELS" ]; then
    mkdir -p ~/.cache/warp && xz -dc "$KERNELS" | tar x -C ~/.cache/warp --skip-old-files
    echo "kernel cache: $(ls ~/.cache/warp/1.19.0 2>/dev/null | wc -l) modules"
  else
    echo "WARNING: no precompiled CUDA kernels at $KERNELS: expect ~13 min of compilation first" >&2
  fi
}
# unpack_wheels IMPORTS: the packed wheels (/tmp/gpu/part-*) into /tmp/site, the kernels into place, then an import
# check of IMPORTS (a python statement) and the GPU's state
unpack_wheels() {
  cat /tmp/gpu/part-* | xz -dc -T0 | tar x -C / || exit 1
  unpack_kernels
  python -c "$1" || exit 1
  nvidia-smi --query-gpu=name,memory.used --format=csv
}
# latest_model DIR: DIR when its training finished, else DIR.latest made of the cut run's last weights (DIR.partial)
latest_model() {
  if [ -f "$1/model.safetensors" ]; then echo "$1"; return; fi
  mkdir -p "$1.latest" && cp "$1.partial/last.safetensors" "$1.latest/model.safetensors" &&
    cp "$1.partial/last.json" "$1.latest/model.json" && echo "$1.latest"
}
# fresh_lift_data EPISODES ATTEMPTS SIM_MINUTES VAL TEST: lift_handle episodes simulated with Newton (WORLDS worlds per
# batch, default 64) and validated into $R/store.zarr (world_model.sh data), VAL + TEST whole episodes held out
fresh_lift_data() {
  export TASKS="[lift_handle]" EPISODES=$1 ATTEMPTS=$2 SIM_MINUTES=$3 VAL_PER_TASK=$4 TEST_PER_TASK=$5 \
    WORLDS=${WORLDS:-64} WORKERS=1 TRAIN=0
  step "data start"
  bash scripts/gpu/world_model.sh data > $R/data.log 2>&1
  step "data rc=$? $(tail -c 300 $R/data.log | tr '\r\n' '  ')"
}
# chain TAG MODEL: one batch of generated episodes with MODEL (expand), the teacher check of up to TEACHER plans per
# verdict (TEACHER_PERTURB: Newton re-runs), and the held-out 100-frame rollouts (expand_check_rollouts.sh)
chain() {
  TAG=$1 MODEL=$2 SELF_CONTACT=true EXPAND_MINUTES=1.0 EXPAND_BATCH=${EXPAND_BATCH:-64} TEACHER=${TEACHER:-32} \
    STAB_PER_TASK=8 EXPAND_TIMEOUT=600 TEACHER_TIMEOUT=600 EVAL_TIMEOUT=400 \
    bash scripts/gpu/expand_check_rollouts.sh > $R/chain_$1.log 2>&1
  step "chain $1 rc=$? $(tail -c 400 $R/chain_$1.log | tr '\r\n' '  ')"
}
