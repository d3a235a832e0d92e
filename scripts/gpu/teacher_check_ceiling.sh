#!/bin/bash
# The teacher check's ceiling on one GPU. Fresh Newton lift_handle data, one batch of generated episodes with the
# shipped model, then the teacher check with Newton replaying every plan again (another batch order; frame-0
# positions + N(0, s^2) for each s in PERTURB): how often Newton agrees with itself bounds what any model can reach.
# Run in the background (hold_lib.sh `background`) once the packages are in place; progress in /tmp/run/steps.log.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
fresh_lift_data ${EPISODES:-64} ${ATTEMPTS:-64} ${SIM_MINUTES:-2} 2 2
source scripts/gpu/gpu_overrides.sh
TAG=ceiling MODEL=models/pretrained/worldcontact-lift-handle SELF_CONTACT=true EXPAND_MINUTES=1.0 EXPAND_BATCH=64 \
  SKIP_TEACHER=1 SKIP_EVAL=1 EXPAND_TIMEOUT=500 bash scripts/gpu/expand_check_rollouts.sh > $R/expand.log 2>&1
step "expand rc=$? $(tail -c 300 $R/expand.log | tr '\r\n' '  ')"
timeout ${TEACHER_TIMEOUT:-900} python -m stages.teacher_check --params params.yaml "${EXP_SETS[@]}" \
  --set sim.worlds=${TEACHER_WORLDS:-32} --store $R/expanded_ceiling.zarr --rejected $R/rejected_ceiling.zarr \
  --limit ${TEACHER:-40} --newton-perturb-m ${PERTURB:-0 0.0003 0.001} --report $OUT/teacher_check_ceiling.json \
  > $R/teacher.log 2>&1
step "teacher rc=$? $(tail -c 600 $R/teacher.log | tr '\r\n' '  ')"
step "DONE"
