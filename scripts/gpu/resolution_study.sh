#!/bin/bash
# How fine a bag the scene needs: benchmarks.resolution on the GPU, the same TASK plans (default lift_handle; NAME names
# the report, e.g. h200_bag_drop) in Newton at each bag resolution (RESOLUTIONS, each VERTICES[:key=value,...]: the
# finer bags with their time step, contact radii and pinch scaled to their edges), PLANS plans (default 32), WORLDS worlds per batch (default 64), ITERATIONS VBD iterations
# (default 20: converged lifts at 306 vertices). Run in the background (hold_lib.sh `background`) once the packages and
# kernels are in place (hold_lib.sh `unpack_wheels`); progress in /tmp/run/steps.log, the report in
# $OUT/resolution_$NAME.{json,md,png}.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
FINE="sim.bag.particle_radius_m=0.002,sim.self_contact_margin_m=0.0015,sim.self_contact_gap_m=0.001"
FINE="$FINE,tasks.common.closed_m=0.002,validate.penetration_tol_m=0.004"
# the step shrinks with the edge: at ~1,200 vertices the 2 ms step lost the strap in every lift, 1 ms held it (CPU)
[ -n "${RESOLUTIONS+x}" ] || RESOLUTIONS=(300 "1200:sim.dt_s=0.001,sim.substeps=40"
  "2500:sim.dt_s=0.0005,sim.substeps=80" "5000:$FINE,sim.dt_s=0.0005,sim.substeps=80")
ARGS=()
for r in "${RESOLUTIONS[@]}"; do ARGS+=(--resolution "$r"); done
step "resolution study start: ${RESOLUTIONS[*]}"
timeout ${STUDY_TIMEOUT:-1500} python -m benchmarks.resolution --params params.yaml --set sim.device=cuda \
  --set validate.device=cuda --set sim.iterations=${ITERATIONS:-20} --set sim.worlds=${WORLDS:-64} \
  --task ${TASK:-lift_handle} --plans ${PLANS:-32} "${ARGS[@]}" --out $OUT/resolution_${NAME:-h200}.json > $R/resolution.log 2>&1
step "resolution study rc=$? $(tr '\r' '\n' < $R/resolution.log | grep "vertices:" | tr '\n' ' ')"
step "DONE"
