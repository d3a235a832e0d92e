#!/bin/bash
# The world model's expansion checks on the GPU, with MODEL (default /tmp/run/model, world_model_chunk.sh's): the lift_handle
# expansion (expand.pad_carry=${PAD_CARRY:-false}), the teacher check of up to TEACHER plans of each verdict, and the
# held-out 100-frame rollouts of the model against constant velocity and zero motion (evaluate's stability curves).
# Reports to $OUT (TAG names them).
cd "$(dirname "$0")/../.."
source scripts/gpu/gpu_overrides.sh
TAG=${TAG:-h100}
MODEL=${MODEL:-/tmp/run/model}
if [ "${SKIP_EXPAND:-0}" != 1 ]; then
timeout ${EXPAND_TIMEOUT:-300} python -m stages.expand --params params.yaml "${EXP_SETS[@]}" --model "$MODEL" \
  --store /tmp/run/store.zarr --out /tmp/run/expanded_$TAG.zarr --rejected-out /tmp/run/rejected_$TAG.zarr \
  --report $OUT/expand_$TAG.json 2>&1 | tr '\r' '\n' | grep -v "it/s\]$" | tail -4
fi
if [ "${SKIP_TEACHER:-0}" != 1 ]; then
timeout ${TEACHER_TIMEOUT:-240} python -m stages.teacher_check --params params.yaml "${EXP_SETS[@]}" \
  --store /tmp/run/expanded_$TAG.zarr --rejected /tmp/run/rejected_$TAG.zarr --limit ${TEACHER:-40} \
  ${TEACHER_PERTURB:+--newton-perturb-m $TEACHER_PERTURB} --report $OUT/teacher_check_$TAG.json 2>&1 | tr '\r' '\n' | grep -v "it/s\]$" | tail -4
fi
if [ "${SKIP_EVAL:-0}" != 1 ]; then
timeout ${EVAL_TIMEOUT:-200} python -m stages.evaluate --params params.yaml --store /tmp/run/store.zarr \
  --set evaluate.device=cuda --set evaluate.stability_frames=100 --set evaluate.stability_per_task=${STAB_PER_TASK:-2} \
  --set "evaluate.methods={worldcontact: {kind: worldcontact, path: $MODEL}, constant_velocity: {kind: constant_velocity}, zero_motion: {kind: zero_motion}}" \
  --metrics $OUT/heldout_metrics_$TAG.json --stability-csv $OUT/heldout_stability_$TAG.csv \
  --stability-png /tmp/run/stability_$TAG.png 2>&1 | tail -4
fi
