#!/bin/bash
# Issue 19: the joint projection's final edge-only passes (expand.projection_final_edge_passes) against none, on the
# same fresh Newton lift_handle data and the shipped model: one batch of 64 generated episodes per PASSES value, and the teacher
# check of up to 25 plans of each verdict. Run in the background (hold_lib.sh `background`) after the wheels are
# unpacked; progress in /tmp/run/steps.log, reports in /tmp/run/out.
cd "$(dirname "$0")/../.."
R=/tmp/run; mkdir -p $R/out; export OUT=$R/out
step() { echo "$(date +%T) $*" >> $R/steps.log; }
export TASKS="[lift_handle]" EPISODES=${EPISODES:-48} ATTEMPTS=96 WORLDS=48 WORKERS=1 TRAIN=0 SIM_MINUTES=4
step "data start"
bash scripts/gpu/issue19_hold.sh data > $R/data.log 2>&1
step "data rc=$? $(tail -c 400 $R/data.log | tr '\r\n' '  ')"
export MODEL=models/pretrained/worldcontact-lift-handle SELF_CONTACT=true EXPAND_MINUTES=1.0 EXPAND_BATCH=64 \
  TEACHER=25 SKIP_EVAL=1 EXPAND_TIMEOUT=420 TEACHER_TIMEOUT=300
for passes in ${PASSES:-0 50 200}; do
  TAG=passes$passes EXTRA_EXP_SETS="--set expand.projection_final_edge_passes=$passes" \
    bash scripts/gpu/issue19_expand.sh > $R/expand_$passes.log 2>&1
  step "passes $passes rc=$? $(tail -c 500 $R/expand_$passes.log | tr '\r\n' '  ')"
done
step "DONE"
