#!/bin/bash
# A lift_handle world model for a finer bag, on one GPU: fresh Newton lift_handle episodes with the bag at VERTICES
# (default 1200) and the step it needs (SCENE, default 1 ms with 40 substeps: the resolution study's setting, frames
# still 40 ms), converged (ITERATIONS, default 20), validated (4 val + 4 test whole episodes); then the shipped lift
# model (INIT, default models/pretrained/worldcontact-lift-handle: the network carries no vertex count) fine-tuned on
# them for MAX_MINUTES (default 6; BASE_STEPS, PROJ_STEPS). Run in the background (hold_lib.sh `background`) once the
# packages are in place (hold_lib.sh `unpack_wheels`); progress in /tmp/run/steps.log; the model, its training report
# and the data's reports in $OUT. The expansion-speed benchmark then runs at this bag with
# MODEL=<the model folder> EXTRA="--set scene.bag.target_vertices=... (SCENE)" scripts/gpu/expand_speed.sh.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
export SCENE=${SCENE:-"scene.bag.target_vertices=${VERTICES:-1200} sim.dt_s=0.001 sim.substeps=40"}
export SIM_ITERATIONS=${ITERATIONS:-20}
step "finer bag: $SCENE"
fresh_lift_data ${EPISODES:-96} ${ATTEMPTS:-160} ${SIM_MINUTES:-7} 4 4
cp $R/memory.json "$OUT"/simulate_memory.json 2>/dev/null
STORE=$R/store.zarr CKPT_OUT=$R/ckpt WORK=$R/model MAX_MINUTES=${MAX_MINUTES:-6} INIT_FROM=${INIT:-models/pretrained/worldcontact-lift-handle} \
  BASE_STEPS=${BASE_STEPS:-2000} PROJ_STEPS=${PROJ_STEPS:-500} PEAK_LR=3.0e-5 BASE_WARMUP=500 \
  EXTRA_TRAIN_SETS="--set train.fine_tune_lr_scale=1.0 --set train.eval_every_steps=1000" \
  bash scripts/gpu/world_model_chunk.sh > $R/train.log 2>&1
step "train rc=$? $(tail -c 300 $R/train.log | tr '\r\n' '  ')"
model=$(latest_model $R/model) && cp $model/model.safetensors $model/model.json "$OUT"/ && step "model from $model"
cp $R/ckpt/train.json "$OUT"/train.json 2>/dev/null
step "DONE"
