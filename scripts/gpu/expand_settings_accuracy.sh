#!/bin/bash
# Which of the slot engine's shortcuts costs the expansion its agreement with Newton: the same fresh Newton
# lift_handle data (sim.iterations SIM_ITERATIONS, default 20: converged) and the shipped model, one expansion of PLANS
# (default 80) planned episodes per setting, all settings side by side on the GPU, and the teacher check of every plan
# (Newton replays it at the same iterations). Settings: the slot engine as shipped (bf16 network, fixed 10 + 20
# projection passes, 96 bounded-step pairs per episode), each shortcut undone alone (fp32; 50 + 50 passes; 512 pairs),
# all three undone, and the reference engine (expand.engine=batches: fp32, passes until within tolerance).
# Run in the background (hold_lib.sh `background`) once the packages are in place; progress in /tmp/run/steps.log,
# reports (expand_<setting>.json, teacher_check_<setting>.json) in $OUT.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
export SIM_ITERATIONS=${SIM_ITERATIONS:-20}
# the slot engine's CUDA kernels compile once, beside the data, before the settings share them
(python -m benchmarks.expand_smoke --device cuda --slots 4 --frames 10 --out $OUT/smoke.json > $R/smoke.log 2>&1
 step "smoke rc=$?") &
WORLDS=64 fresh_lift_data ${EPISODES:-32} 96 4 2 2
wait
export MODEL=${MODEL:-models/pretrained/worldcontact-lift-handle} SELF_CONTACT=true EXPAND_MINUTES=0 EXPAND_BATCH=64 \
  TARGET=1000 ATTEMPTS_EXPAND=${PLANS:-80} TEACHER=${PLANS:-80} SKIP_EVAL=1 EXPAND_TIMEOUT=1200 TEACHER_TIMEOUT=900
# setting TAG: one expansion and its teacher check, with the overrides in EXTRA_EXP_SETS
setting() {
  TAG=$1 EXTRA_EXP_SETS=${EXTRA_EXP_SETS:-} bash scripts/gpu/expand_check_rollouts.sh > $R/setting_$1.log 2>&1
  step "$1 rc=$? $(tail -c 300 $R/setting_$1.log | tr '\r\n' '  ')"
}
EXTRA_EXP_SETS="" setting slots &
EXTRA_EXP_SETS="--set expand.slots.bf16=false" setting fp32 &
EXTRA_EXP_SETS="--set expand.slots.iterations=50 --set expand.slots.final_edge_passes=50" setting passes50 &
EXTRA_EXP_SETS="--set expand.slots.pair_capacity=512 --set expand.slots.self_contact_capacity=256" setting pairs512 &
EXTRA_EXP_SETS="--set expand.slots.bf16=false --set expand.slots.iterations=50 --set expand.slots.final_edge_passes=50 --set expand.slots.pair_capacity=512 --set expand.slots.self_contact_capacity=256" setting all_undone &
EXTRA_EXP_SETS="--set expand.engine=batches" setting reference &
wait
step "DONE"
