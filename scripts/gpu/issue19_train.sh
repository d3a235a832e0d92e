#!/bin/bash
# One chunk (MAX_MINUTES) of issue 19's world-model training on /tmp/run/store.zarr; run again until it exits 0.
cd "$(dirname "$0")/../.."
source scripts/gpu/issue19_env.sh
STORE=${STORE:-/tmp/run/store.zarr} CKPT_OUT=${CKPT_OUT:-$OUT} WORK=${WORK:-/tmp/run/model} MAX_MINUTES=${MAX_MINUTES:-8.3} \
  scripts/gpu/train_chunk.sh --params params.yaml "${TRAIN_SETS[@]}"
