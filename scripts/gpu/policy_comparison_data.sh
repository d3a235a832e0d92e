#!/bin/bash
# The policy comparison's data on one GPU (run in the background by policy_comparison.sh data; progress in /tmp/run/steps.log):
#   1. Newton: lift_handle episodes of the CPU-default scene (WORLDS worlds a batch) until NEWTON_WANTED are accepted,
#      validated; the first 25 accepted -> source.zarr, the next 125 -> newton_extra.zarr (fresh Newton episodes)
#   2. WorldContact: the shipped model (MODEL) expands source.zarr's 25 to 150 (125 generated, accepted)
#   3. render all three stores (params.yaml's 128 x 128 top + wrist views), then the LeRobot datasets
#      /tmp/run/lerobot/{source, expanded, newton_150} (newton_150 = source + newton_extra)
# Steps 1 and 2 run alone on the GPU, one after the other: their wall times are the data-production times compared.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
MODEL=${MODEL:-models/pretrained/worldcontact-lift-handle}
GPU=(--set sim.device=cuda --set validate.device=cuda)
step "simulate start"
python -m stages.simulate --params params.yaml "${GPU[@]}" --set sim.worlds=${WORLDS:-128} --set agent.workers=1 \
  --set "agent.tasks=[lift_handle]" --set agent.episodes_per_task=${NEWTON_WANTED:-150} \
  --set agent.max_attempts_per_task=${NEWTON_ATTEMPTS:-512} --out $R/raw.zarr --report $R/simulate.json \
  --memory $R/memory.json > $R/simulate.log 2>&1
step "simulate rc=$? $(tail -c 300 $R/simulate.log | tr '\r\n' '  ')"
python -m stages.validate --params params.yaml "${GPU[@]}" --raw $R/raw.zarr --out $R/newton.zarr \
  --report $R/validate.json > $R/validate.log 2>&1
step "validate rc=$? $(tail -2 $R/validate.log | tr '\n' ' ')"
python -m wc.data.take $R/newton.zarr $R/source.zarr -n 25 --task lift_handle >> $R/steps.log 2>&1
python -m wc.data.take $R/newton.zarr $R/newton_extra.zarr -n 125 --skip 25 --task lift_handle --at-most >> $R/steps.log 2>&1
step "expand start"
python -m stages.expand --params params.yaml "${GPU[@]}" --set expand.device=cuda --set expand.target_trajectories=150 \
  --set expand.max_attempts=${EXPAND_ATTEMPTS:-400} --set expand.batch_size=${EXPAND_BATCH:-64} \
  --set expand.max_minutes=${EXPAND_MINUTES:-9} --model $MODEL --store $R/source.zarr --out $R/expanded.zarr \
  --rejected-out $R/rejected.zarr --report $R/expand.json > $R/expand.log 2>&1
step "expand rc=$? $(tail -c 400 $R/expand.log | tr '\r\n' '  ')"
RS=(--set render.device=cuda)
for s in source expanded newton_extra; do
  python -m stages.render --params params.yaml "${RS[@]}" --inputs $R/$s.zarr --outs $R/frames_$s.zarr \
    --report $R/render_$s.json --sheet $R/sheet_$s.png > $R/render_$s.log 2>&1 &
done
wait
step "render done $(tail -qn1 $R/render_*.log | tr '\r\n' '  ' | tail -c 400)"
python -m stages.dataset --params params.yaml --source-trajectories $R/source.zarr --source-frames $R/frames_source.zarr \
  --expanded-trajectories $R/expanded.zarr --expanded-frames $R/frames_expanded.zarr --out $R/lerobot \
  --report $R/dataset.json > $R/dataset.log 2>&1 &
python -m stages.dataset --params params.yaml --set dataset.expanded_arm=newton_150 --source-trajectories $R/source.zarr \
  --source-frames $R/frames_source.zarr --expanded-trajectories $R/newton_extra.zarr \
  --expanded-frames $R/frames_newton_extra.zarr --out $R/lerobot_newton --report $R/dataset_newton.json > $R/dataset_newton.log 2>&1 &
wait
mv $R/lerobot_newton/newton_150 $R/lerobot/newton_150
step "datasets done $(ls $R/lerobot) $(du -sh $R/lerobot | cut -f1)"
step "DONE"
