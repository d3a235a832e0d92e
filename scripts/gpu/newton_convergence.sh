#!/bin/bash
# Is the source simulator reproducible enough to be a teacher? benchmarks.newton_convergence on the GPU:
# the same lift_handle specs (the CPU default scene, 306-vertex bag) at several VBD iteration counts, each rolled out
# once and re-run in another batch order and from frame-0 noise (PERTURB), against its cost per episode.
# Run in the background (hold_lib.sh `background`) once the packages are in place; progress in /tmp/run/steps.log.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
step "convergence start"
# shellcheck disable=SC2086  # PERTURB is a list
timeout ${CONV_TIMEOUT:-1500} python -m benchmarks.newton_convergence --params params.yaml --set sim.device=cuda \
  --set validate.device=cuda --set sim.worlds=${WORLDS:-64} --task lift_handle --iterations ${ITERS:-5,20,10,40} \
  --plans ${PLANS:-64} --perturb-m ${PERTURB:-0 0.0003} --out $OUT/newton_convergence_${NAME:-h100}.json > $R/conv.log 2>&1
step "convergence rc=$? $(tr '\r' '\n' < $R/conv.log | grep "iterations:" | tr '\n' ' ')"
step "DONE"
