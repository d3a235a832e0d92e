#!/bin/bash
# World-model data on the GPU: lift_handle and the tasks that share its contacts, simulated with Newton (WORLDS worlds per
# batch, tasks in turn, no batch started after SIM_MINUTES), validated into /tmp/run/store.zarr (2 val + 2 test whole episodes per task); reports to $OUT.
cd "$(dirname "$0")/../.."
source scripts/gpu/gpu_overrides.sh
timeout ${SIM_TIMEOUT:-560} python -m stages.simulate --params params.yaml "${SIM_SETS[@]}" --out /tmp/run/raw.zarr \
  --max-minutes ${SIM_MINUTES:-6} --report $OUT/simulate.json --memory /tmp/run/memory.json > /tmp/run/simulate.log 2>&1
echo "simulate rc=$?; contact buffer overflow lines: $(grep -c overflowed /tmp/run/simulate.log)"
tr '\r' '\n' < /tmp/run/simulate.log | grep -v "it/s\]$" | tail -8
python -m stages.validate --params params.yaml "${VAL_SETS[@]}" --raw /tmp/run/raw.zarr --out /tmp/run/store.zarr \
  --report $OUT/validate.json 2>&1 | tail -4
