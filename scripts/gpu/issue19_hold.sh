#!/bin/bash
# Issue 19 in one GPU hold, as calls of at most 10 minutes (the machine is bare at every start).
# CUDA kernels: KERNELS (default: the committed scripts/gpu/kernel_cache/ build for warp 1.19.0, newton 1.8.0, sm_90,
# from precompile_cuda_kernels.py); without them the first simulate compiles for ~13 min.
# Several simulate processes share the GPU (WORKERS, one task each): 4 gave 4.1x and 8 gave 5.6x the episodes per
# minute of one (reports/gpu/simulate_workers_h100.json).
#   issue19_hold.sh data     the precompiled CUDA kernels into place, the data (issue19_data.sh), then the training started in the background
#                            (issue19_train.sh, one chunk of MAX_MINUTES, resumed from CKPT_IN's parts if set; it outlives this call)
#   issue19_hold.sh wait S   wait up to S seconds for that training; its report and model files to $OUT
#                            (TRAIN=0: the data only)
#   issue19_hold.sh finish   issue19_expand.sh on MODEL, else the finished model (else the partial run's latest weights)
cd "$(dirname "$0")/../.."
export PYTHONPATH=/tmp/site:$PWD
mkdir -p /tmp/run "$OUT"
latest_model() {  # the finished model folder, else the partial run's latest weights made one (/tmp/run/model.latest)
  if [ -f /tmp/run/model/model.safetensors ]; then echo /tmp/run/model; return; fi
  mkdir -p /tmp/run/model.latest
  cp /tmp/run/model.partial/last.safetensors /tmp/run/model.latest/model.safetensors &&
    cp /tmp/run/model.partial/last.json /tmp/run/model.latest/model.json && echo /tmp/run/model.latest
}
case "$1" in
  data)
    kernels=${KERNELS:-scripts/gpu/kernel_cache/warp-1.19.0_newton-1.8.0_sm90.tar.xz}
    if [ -f "$kernels" ]; then
      mkdir -p ~/.cache/warp && xz -dc "$kernels" | tar x -C ~/.cache/warp --skip-old-files
      echo "kernel cache: $(ls ~/.cache/warp/1.19.0 | wc -l) modules"
    else
      echo "WARNING: no precompiled CUDA kernels at $kernels: expect ~13 min of compilation first" >&2
    fi
    WORLDS=${WORLDS:-8} WORKERS=${WORKERS:-6} SIM_MINUTES=${SIM_MINUTES:-4} bash scripts/gpu/issue19_data.sh
    [ "${TRAIN:-1}" = 0 ] && exit 0  # data only (the model comes from elsewhere: MODEL=... for finish)
    CKPT_OUT=/tmp/run/ckpt setsid nohup bash scripts/gpu/issue19_train.sh > /tmp/run/train_bg.log 2>&1 < /dev/null &
    echo $! > /tmp/run/train_bg.pid
    sleep 20; tail -3 /tmp/run/ckpt/train.log 2>/dev/null ;;
  wait)
    end=$((SECONDS + ${2:-500}))
    while kill -0 "$(cat /tmp/run/train_bg.pid)" 2>/dev/null && [ $SECONDS -lt $end ]; do sleep 10; done
    tail -4 /tmp/run/ckpt/train.log; tail -3 /tmp/run/train_bg.log
    cp /tmp/run/ckpt/train.json /tmp/run/ckpt/train_loss.csv "$OUT"/ 2>/dev/null
    model=$(latest_model) && cp $model/model.safetensors $model/model.json "$OUT"/ && echo "model from $model" ;;
  finish)
    MODEL=${MODEL:-$(latest_model)} bash scripts/gpu/issue19_expand.sh ;;
  *) echo "usage: $0 data | wait SECONDS | finish" >&2; exit 2 ;;
esac
