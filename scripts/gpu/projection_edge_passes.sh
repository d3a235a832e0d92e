#!/bin/bash
# The joint projection's final edge-only passes (expand.projection_final_edge_passes) against none, on the
# same fresh Newton lift_handle data and the shipped model: one batch of 64 generated episodes per PASSES value, and the teacher
# check of up to 25 plans of each verdict. Run in the background (hold_lib.sh `background`) once the
# packages are in place; progress in /tmp/run/steps.log, reports in /tmp/run/out.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
WORLDS=48 fresh_lift_data ${EPISODES:-48} 96 4 2 2
export MODEL=models/pretrained/worldcontact-lift-handle SELF_CONTACT=true EXPAND_MINUTES=1.0 EXPAND_BATCH=64 \
  TEACHER=25 SKIP_EVAL=1 EXPAND_TIMEOUT=420 TEACHER_TIMEOUT=300
for passes in ${PASSES:-0 50 200}; do
  TAG=passes$passes EXTRA_EXP_SETS="--set expand.projection_final_edge_passes=$passes" \
    bash scripts/gpu/expand_check_rollouts.sh > $R/expand_$passes.log 2>&1
  step "passes $passes rc=$? $(tail -c 500 $R/expand_$passes.log | tr '\r\n' '  ')"
done
step "DONE"
