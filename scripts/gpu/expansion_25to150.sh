#!/bin/bash
# The paper's 25 -> 150 lift_handle expansion in one configuration on one GPU: fresh lift_handle data at
# SIM_ITERATIONS (default 20) VBD iterations, the first 25 accepted episodes expanded to 150 with the shipped model (nothing else on the GPU while
# it runs, so its trajectories per minute are its own), then, side by side, the teacher check of every generated plan
# at the same iterations, Newton re-run on the first RERUN plans in another batch order (its own ceiling), and the
# shipped model's 100-frame rollouts of the held-out episodes (all of them are: it never saw this data) against
# constant velocity; last the rest-features A/B (model.rest_features off and on, trained from scratch on this data
# side by side for AB_MINUTES, scored on the same held-out rollouts). The order of the 2026-11-27 run
# (reports/gpu/lift_expansion.md). Run in the background (hold_lib.sh `background`) once the packages are in place,
# ~20 min on an H100; progress in /tmp/run/steps.log, reports in /tmp/run/out.
cd "$(dirname "$0")/../.."
export SIM_ITERATIONS=${SIM_ITERATIONS:-20}
source scripts/gpu/hold_lib.sh
SHIPPED=models/pretrained/worldcontact-lift-handle
fresh_lift_data ${EPISODES:-64} ${ATTEMPTS:-96} ${SIM_MINUTES:-3} 4 8
mv $OUT/simulate.json $OUT/simulate_final.json; mv $OUT/validate.json $OUT/validate_final.json
source scripts/gpu/gpu_overrides.sh

TAG=final MODEL=$SHIPPED SELF_CONTACT=true TARGET=150 EXPAND_MINUTES=${EXPAND_MINUTES:-9} EXPAND_BATCH=64 \
  EXPAND_TIMEOUT=900 EXTRA_EXP_SETS="--set expand.max_sources=25" SKIP_TEACHER=1 SKIP_EVAL=1 \
  bash scripts/gpu/expand_check_rollouts.sh > $R/expand_final.log 2>&1
step "expand rc=$? $(tail -c 400 $R/expand_final.log | tr '\r\n' '  ')"

# side by side: Newton replays every generated plan (the teacher check), and once more the first RERUN of them in
# another batch order (Newton against itself); the shipped model's held-out rollouts
teacher() {  # teacher NAME LIMIT [--newton-perturb-m 0]: the teacher check of the first LIMIT plans of each store
  timeout 700 python -m stages.teacher_check --params params.yaml "${EXP_SETS[@]}" --store $R/expanded_final.zarr \
    --rejected $R/rejected_final.zarr --limit $2 "${@:3}" --report $OUT/teacher_check_$1.json > $R/teacher_$1.log 2>&1
  step "teacher $1 rc=$? $(tail -c 400 $R/teacher_$1.log | tr '\r\n' '  ')"
}
teacher final_all ${TEACHER:-150} & teacher final_rerun ${RERUN:-56} --newton-perturb-m 0 &
TAG=final MODEL=$SHIPPED STAB_PER_TASK=8 EVAL_TIMEOUT=400 SKIP_EXPAND=1 SKIP_TEACHER=1 \
  bash scripts/gpu/expand_check_rollouts.sh > $R/eval_final.log 2>&1
step "eval final rc=$? $(tail -c 300 $R/eval_final.log | tr '\r\n' '  ')"
wait

ab() {  # ab TAG REST_FEATURES: a from-scratch model on this data for AB_MINUTES, then its held-out rollouts
  STORE=$R/store.zarr CKPT_OUT=$R/train_$1 WORK=$R/model_$1 MAX_MINUTES=${AB_MINUTES:-3.2} INIT_FROM= \
    BASE_STEPS=${AB_BASE:-4000} PROJ_STEPS=${AB_PROJ:-1000} BASE_WARMUP=500 \
    EXTRA_TRAIN_SETS="--set model.rest_features=$2 --set train.eval_every_steps=500" \
    bash scripts/gpu/world_model_chunk.sh > $R/train_$1.log 2>&1
  step "train $1 rc=$? $(tail -c 200 $R/train_$1.log | tr '\r\n' '  ')"
  model=$(latest_model $R/model_$1)
  [ "$model" = $R/model_$1 ] || { cp $model/model.json $OUT/train_$1_last.json; step "$1: partial model"; }
  TAG=$1 MODEL=$model SKIP_EXPAND=1 SKIP_TEACHER=1 STAB_PER_TASK=8 EVAL_TIMEOUT=400 \
    bash scripts/gpu/expand_check_rollouts.sh > $R/eval_$1.log 2>&1
  step "eval $1 rc=$?"
}
if [ "${AB:-1}" = 1 ]; then ab rest_features_off false & ab rest_features_on true & wait; fi
step "DONE"
