#!/bin/bash
# The world model's data, training and expansion checks on one GPU, as device calls of at most 10 minutes (the
# machine is bare at every start).
# Several simulate processes share the GPU (WORKERS, one task each): 4 gave 4.1x and 8 gave 5.6x the episodes per
# minute of one (reports/gpu/simulate_workers_h100.json).
#   world_model.sh data     the precompiled CUDA kernels into place (hold_lib.sh unpack_kernels), the data
#                                (contact_tasks_data.sh), then the training started in the background
#                                (world_model_chunk.sh, one chunk of MAX_MINUTES, resumed from CKPT_IN's parts if set;
#                                it outlives this call; TRAIN=0: the data only)
#   world_model.sh wait S   wait up to S seconds for that training; its report and model files to $OUT
#   world_model.sh finish   expand_check_rollouts.sh on MODEL, else the finished model (else the cut run's latest weights)
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
case "$1" in
  data)
    unpack_kernels
    WORLDS=${WORLDS:-8} WORKERS=${WORKERS:-6} SIM_MINUTES=${SIM_MINUTES:-4} bash scripts/gpu/contact_tasks_data.sh
    [ "${TRAIN:-1}" = 0 ] && exit 0  # data only (the model comes from elsewhere: MODEL=... for finish)
    CKPT_OUT=/tmp/run/ckpt setsid nohup bash scripts/gpu/world_model_chunk.sh > /tmp/run/train_bg.log 2>&1 < /dev/null &
    echo $! > /tmp/run/train_bg.pid
    sleep 20; tail -3 /tmp/run/ckpt/train.log 2>/dev/null ;;
  wait)
    end=$((SECONDS + ${2:-500}))
    while kill -0 "$(cat /tmp/run/train_bg.pid)" 2>/dev/null && [ $SECONDS -lt $end ]; do sleep 10; done
    tail -4 /tmp/run/ckpt/train.log; tail -3 /tmp/run/train_bg.log
    cp /tmp/run/ckpt/train.json /tmp/run/ckpt/train_loss.csv "$OUT"/ 2>/dev/null
    model=$(latest_model /tmp/run/model) && cp $model/model.safetensors $model/model.json "$OUT"/ && echo "model from $model" ;;
  finish)
    MODEL=${MODEL:-$(latest_model /tmp/run/model)} bash scripts/gpu/expand_check_rollouts.sh ;;
  *) echo "usage: $0 data | wait SECONDS | finish" >&2; exit 2 ;;
esac
