#!/bin/bash
# One chunk (MAX_MINUTES) of the world-model training of gpu_overrides.sh on /tmp/run/store.zarr; run again until it exits 0.
cd "$(dirname "$0")/../.."
source scripts/gpu/gpu_overrides.sh
STORE=${STORE:-/tmp/run/store.zarr} CKPT_OUT=${CKPT_OUT:-$OUT} WORK=${WORK:-/tmp/run/model} MAX_MINUTES=${MAX_MINUTES:-8.3} \
  scripts/gpu/train_chunk.sh --params params.yaml "${TRAIN_SETS[@]}"
