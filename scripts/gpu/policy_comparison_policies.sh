#!/bin/bash
# The policy comparison's three policies on one GPU (run in the background by policy_comparison.sh policies; progress in
# /tmp/run/steps.log), from the datasets /tmp/run/lerobot/{source, expanded, newton_150} of policy_comparison_data.sh:
#   1. ACT (params/policy_act_gpu.yaml, identical settings and seed) on each dataset, the three trainings side by side
#      (the video decoding bounds each; NUM_WORKERS decoder processes each)
#   2. policy_eval: TRIALS closed-loop Newton trials per policy on the same trial seeds (the policy seed stream),
#      in EVAL_WORKERS processes sharing the GPU
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
ARMS=${ARMS:-source expanded newton_150}
step "finetune start: $ARMS"
for arm in $ARMS; do
  python -m stages.finetune --params params.yaml --policy params/policy_act_gpu.yaml --set "policy.datasets=[$arm]" \
    --set policy.num_workers=${NUM_WORKERS:-5} --set policy.steps=${STEPS:-3500} --set policy.decay_steps=${STEPS:-3500} \
    --data-root $R/lerobot --out-root $R/policy --report $R/finetune_$arm.json > $R/finetune_$arm.log 2>&1 &
done
wait
step "finetune done $(for arm in $ARMS; do tail -c 300 $R/finetune_$arm.log | tr '\r\n' '  ' | tail -c 200; done)"
list=$(echo $ARMS | sed 's/ /, /g')
python -m stages.policy_eval --params params.yaml --set policy_eval.device=cuda --set policy_eval.trials=${TRIALS:-50} \
  --set policy_eval.workers=${EVAL_WORKERS:-12} --set policy_eval.videos=2 --set "policy.datasets=[$list]" \
  --models-root $R/policy --report $R/policy.json --videos $R/videos --table $R/policy_success.csv \
  --plot $R/policy_success.png > $R/policy_eval.log 2>&1
step "policy_eval rc=$? $(tail -c 300 $R/policy_eval.log | tr '\r\n' '  ')"
step "DONE"
