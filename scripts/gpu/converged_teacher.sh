#!/bin/bash
# The world model against a converged teacher, on one GPU. At params.yaml's 5 VBD iterations about half of Newton's own
# lifts slip out of the pads and a re-run moves a plan 31 mm; at 20 none slip and a re-run moves it 7 mm
# (reports/gpu/newton_convergence_h100.md). One GPU run: fresh lift_handle data at SIM_ITERATIONS (default 20), the
# shipped model (or START_MODEL) fine-tuned on it (the shipped recipe: window 5, batch 8, 3,000 + 1,000 steps, peak lr 3e-5), then the
# shipped and the fine-tuned model each: one batch of generated episodes, the teacher check at the same iterations
# with Newton re-run once in another batch order (its own ceiling on these plans), and the held-out 100-frame
# rollouts against constant velocity. Run in the background (hold_lib.sh `background`) once the
# packages are in place; progress in /tmp/run/steps.log, reports in /tmp/run/out.
cd "$(dirname "$0")/../.."
export SIM_ITERATIONS=${SIM_ITERATIONS:-20} TEACHER_PERTURB=0  # chain: Newton re-run once
source scripts/gpu/hold_lib.sh
SHIPPED=${START_MODEL:-models/pretrained/worldcontact-lift-handle}  # the model fine-tuned and compared against
fresh_lift_data ${EPISODES:-192} ${ATTEMPTS:-256} ${SIM_MINUTES:-4} 4 8
cp /tmp/run/out/simulate.json $OUT/simulate_it$SIM_ITERATIONS.json; cp /tmp/run/out/validate.json $OUT/validate_it$SIM_ITERATIONS.json
source scripts/gpu/gpu_overrides.sh

chain shipped_it$SIM_ITERATIONS $SHIPPED &
STORE=$R/store.zarr CKPT_OUT=$R/train_ft WORK=$R/model_ft MAX_MINUTES=${TRAIN_MINUTES:-7.5} INIT_FROM=$SHIPPED BATCH=8 \
  BASE_STEPS=3000 PROJ_STEPS=1000 PEAK_LR=3.0e-5 BASE_WARMUP=500 \
  EXTRA_TRAIN_SETS="--set train.fine_tune_lr_scale=1.0 --set train.window=5 --set train.eval_every_steps=1000" \
  bash scripts/gpu/world_model_chunk.sh > $R/train_ft.log 2>&1
step "train ft rc=$? $(tail -c 300 $R/train_ft.log | tr '\r\n' '  ')"
cp $R/train_ft/train.json $OUT/train_ft_it$SIM_ITERATIONS.json 2>/dev/null
model=$(latest_model $R/model_ft); [ "$model" = $R/model_ft ] || step "ft: partial model"
mkdir -p $OUT/model_ft && cp $model/model.safetensors $model/model.json $OUT/model_ft/
wait
chain ft_it$SIM_ITERATIONS $model
step "DONE"
