#!/bin/bash
# The source arm of the policy comparison on one GPU (one machine, commands back to back): PHASE=A simulate 25 wanted lift_handle episodes, validate,
# render 224^2; PHASE=B LeRobot dataset + ACT (params/policy_act_gpu.yaml); PHASE=C 20 closed-loop trials. Needs the
# packed warp/newton/zarr and lerobot wheels on PYTHONPATH (README: GPU machine); state lives in /tmp/run
cd "$(dirname "$0")/../.."
R="--set render.device=cuda --set render.width=224 --set render.height=224"
case "$PHASE" in
A)
  SIM_TIMEOUT=300 bash scripts/gpu/lift_handle_25.sh
  timeout 200 python -m stages.render --params params.yaml $R --inputs /tmp/run/lift25.zarr --outs /tmp/run/rendered.zarr \
    --report $OUT/render.json --sheet $OUT/render_sheet.png 2>&1 | tr '\r' '\n' | tail -2
  ;;
B)
  timeout 200 python -m stages.dataset --params params.yaml --set dataset.include_expanded=false --set dataset.encoder_threads=0 \
    --source-trajectories /tmp/run/lift25.zarr --source-frames /tmp/run/rendered.zarr --out /tmp/run/lerobot --report $OUT/dataset.json 2>&1 | tr '\r' '\n' | tail -2
  timeout ${FT_TIMEOUT:-540} python -m stages.finetune --params params.yaml --policy params/policy_act_gpu.yaml --set "policy.datasets=[source]" \
    --set policy.steps=${STEPS:-3500} --set policy.decay_steps=${STEPS:-3500} --data-root /tmp/run/lerobot --out-root /tmp/run/policy --report $OUT/finetune.json 2>&1 | tr '\r' '\n' | grep -v "it/s\]$" | tail -4
  ;;
C)
  timeout ${EV_TIMEOUT:-560} python -m stages.policy_eval --params params.yaml $R --set policy_eval.device=cuda --set policy_eval.trials=${TRIALS:-20} \
    --set policy_eval.videos=2 --set "policy.datasets=[source]" --models-root /tmp/run/policy --report $OUT/policy.json \
    --videos $OUT/videos --table $OUT/policy_success.csv --plot $OUT/policy_success.png 2>&1 | tr '\r' '\n' | tail -4
  ;;
esac
ls $OUT
