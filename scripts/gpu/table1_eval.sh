#!/bin/bash
# Table 1, second machine (run in the background by table1.sh eval; progress in /tmp/run/steps.log):
#   1. Newton: fresh test episodes of the same six tasks (agent.seed 23: no model trained on them), TEST_PER_TASK (6) per task
#   2. evaluate every method of params/gpu_table1.yaml on them: Table 1, stability, the speed-accuracy chart
#   3. batched speed: benchmarks.rollout_speed on a test episode (WorldContact fp32 / bf16, B = 1, 8, 32; Newton
#      1 and 32 worlds)
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
P=${P:-params/gpu_table1.yaml}; PER_TASK=${TEST_PER_TASK:-6}  # whole test episodes per task
step "simulate test start"
python -m stages.simulate --params $P --set agent.seed=23 --set agent.episodes_per_task=$((PER_TASK + 1)) \
  --set agent.max_attempts_per_task=32 --out $R/test_raw.zarr --report $R/simulate_test.json \
  --memory $R/memory_test.json > $R/simulate_test.log 2>&1
step "simulate rc=$? $(tail -c 300 $R/simulate_test.log | tr '\r\n' '  ')"
python -m stages.validate --params $P --set validate.val_per_task=0 --set validate.test_per_task=$PER_TASK \
  --raw $R/test_raw.zarr --out $R/test.zarr --report $R/validate_test.json > $R/validate_test.log 2>&1
step "validate rc=$? $(tr "\r" "\n" < $R/validate_test.log | tail -1)"
python -m stages.evaluate --params $P --store $R/test.zarr --metrics $R/metrics.json --stability-csv $R/stability.csv \
  --stability-png $R/stability.png > $R/evaluate.log 2>&1
step "evaluate rc=$? $(tail -16 $R/evaluate.log | tr '\r' '\n' | grep -v 'it/s' | tail -14)"
python -m benchmarks.rollout_speed --params $P --tag table1 --out-dir $R --store $R/test.zarr \
  --checkpoint models/pretrained/worldcontact-lift-handle-stage2/model.safetensors --batches 8,32 --skins 0.002 --profile-frames 0 \
  --train-window 0 --newton-worlds 1,32 \
  --budget-s ${SPEED_BUDGET_S:-300} > $R/rollout_speed.log 2>&1
step "rollout_speed rc=$? $(tail -c 300 $R/rollout_speed.log | tr '\r\n' '  ')"
step "DONE"
