#!/bin/bash
# GPU: 25 wanted lift_handle episodes in the CPU-default scene (8 worlds, at most 96 attempts), validated into
# /tmp/run/lift25.zarr (stays on the machine: too large to come back); reports to $OUT
cd "$(dirname "$0")/../.."
mkdir -p /tmp/run
timeout ${SIM_TIMEOUT:-450} python -m stages.simulate --params params.yaml --set sim.device=cuda --set sim.worlds=8 --set agent.workers=1 \
  --set "agent.tasks=[lift_handle]" --set agent.episodes_per_task=25 --set agent.max_attempts_per_task=96 \
  --out /tmp/run/raw.zarr --report $OUT/simulate_lift25.json --memory /tmp/run/memory.json 2>&1 | tr '\r' '\n' | grep -v "it/s\]$" | tail -15
echo "simulate rc=${PIPESTATUS[0]}"
python -m stages.validate --params params.yaml --raw /tmp/run/raw.zarr --out /tmp/run/lift25.zarr --report $OUT/validate_lift25.json 2>&1 | tail -5
