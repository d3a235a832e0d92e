#!/bin/bash
# GPU world-model training on the default source data (unpacked to /tmp/data/trajectories.zarr); model to $OUT/model
set -x
cd "$(dirname "$0")/../.."
mkdir -p data/source && rm -rf data/source/trajectories.zarr && cp -r /tmp/data/trajectories.zarr data/source/
nvidia-smi --query-gpu=name,memory.used --format=csv
timeout ${TRAIN_TIMEOUT:-540} python -m stages.train --params params.yaml --set train.device=cuda --set train.batch_size=8 \
  --set train.base.steps=${BASE:-1000} --set train.base.warmup_steps=100 --set train.projection.steps=${PROJ:-250} \
  --set train.projection.warmup_steps=25 --set train.eval_every_steps=250 --set train.checkpoint_every_steps=250 --set train.val_windows=64 \
  --out /tmp/gpumodel --report $OUT/train_gpu.json --curves $OUT/train_gpu_loss.csv 2>&1 | tr '\r' '\n' | grep -v "it/s\]$" | tail -40
echo "train rc=${PIPESTATUS[0]}"
mkdir -p $OUT/model
if [ -d /tmp/gpumodel ]; then d=/tmp/gpumodel; else d=/tmp/gpumodel.partial; fi
cp $d/*.json $d/model.safetensors $d/projection.safetensors $d/base.safetensors $OUT/model/  # a cut run lacks model.*: cp says which
ls -la $OUT/model
