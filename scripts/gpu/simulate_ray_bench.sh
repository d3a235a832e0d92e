#!/bin/bash
# Simulate's episodes per minute on the ray executor, 1 worker vs N workers sharing one GPU (N batches of
# one task in flight, ray.gpus_per_unit 1/N, WORLDS Newton worlds each), beside the local executor in-process;
# python -m benchmarks.simulate_ray does the work and writes $OUT_DIR/simulate_ray_$NAME.json and .md.
#   bash scripts/gpu/simulate_ray_bench.sh                     # GPU: workers 1 4 8, 8 worlds each, 1 min per row (~8 min)
# Give it 10 minutes: on a bare H100 (2026-11-26) WORKERS="1 4" MINUTES=0.6 did not finish its warm-up
# and first rows in 290 s (a lift_handle batch runs ~1 min, and each Ray worker imports and builds its world first).
# The JSON and table are rewritten after every row, so a run cut short keeps the rows it finished.
#   DEVICE=cpu WORKERS="1 2" WORLDS=1 TASK=bag_drop MINUTES=0.5 NAME=cpu OUT_DIR=reports \
#     EXTRA="--set tasks.bag_drop.duration_s=0.4" bash scripts/gpu/simulate_ray_bench.sh    # the tiny CPU run
# ray must be importable (it is in requirements.lock; on a machine without network its wheels travel with the others:
# ray==2.60.0 msgpack==1.2.4 jsonschema==4.26.0 jsonschema-specifications==2025.9.1 referencing==0.37.0
# rpds-py==2026.9.1); the precompiled CUDA kernels (KERNELS) go into ~/.cache/warp.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
DEVICE=${DEVICE:-cuda}
if [ "$DEVICE" != cpu ]; then
  unpack_kernels
  nvidia-smi --query-gpu=name,memory.used --format=csv
fi
PY=${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python)}
OUT_DIR=${OUT_DIR:-reports/gpu}
mkdir -p "$OUT_DIR"
# shellcheck disable=SC2086  # WORKERS and EXTRA are word lists
timeout ${TIMEOUT:-580} $PY -m benchmarks.simulate_ray --params ${PARAMS:-params.yaml} --device $DEVICE \
  --workers ${WORKERS:-1 4 8} --worlds ${WORLDS:-8} --task ${TASK:-lift_handle} --minutes ${MINUTES:-1.0} \
  --out "$OUT_DIR/simulate_ray_${NAME:-h100}.json" ${EXTRA:-} 2>&1 | tr '\r' '\n' | grep -v "it/s\]$\|task/s\]$"
exit ${PIPESTATUS[0]}
