#!/bin/bash
# The expansion-speed benchmark (benchmarks/expand_speed.py) on a bare GPU machine, as calls of at most 10 minutes:
#   bash scripts/gpu/expand_speed.sh start   # wheels (/tmp/gpu/part-*) and Newton's kernel cache unpacked, a smoke
#                                            # expansion on the GPU, then the benchmark in the background
#   bash scripts/gpu/expand_speed.sh wait    # wait up to WAIT seconds (default 540); progress and reports to $OUT
# Settings: ITERATIONS (Newton's VBD iterations, default 20: converged lifts), WORLDS (Newton's worlds counts, default
# 32,64,128), SLOTS (expand.batch_size, default 128), PLANNERS (planning processes, default 8), WRITERS (processes
# writing the episodes, expand.write_processes, default 1), NEWTON_S (measured
# Newton seconds per worlds count, default 45), TARGET (expand.target_trajectories of the timed expansion, sources
# included, default 150), TEACHER (generated plans replayed in Newton, default 64), MODEL (the world model's folder,
# default the shipped lift model), EXTRA (more --set overrides), NAME
# (report name, default the GPU's model: h100, h200), SMOKE_SLOTS and SMOKE_FRAMES (the smoke's slot counts, default
# 4,64,128,256: with compile_* each count compiles, ~2 min; and frames, default 40; EXTRA applies to it too).
# PROBE_PLANS > 0: afterwards, Newton alone replays that many lift_handle plans under each probe setting
# (benchmarks/fabric_stretch.py: verdicts, edge stretch, s per episode; PROBE_SETTINGS, one setting, replaces the
# default list: the bag at ~300, ~1,200, ~2,500 and ~5,000 vertices, the finest with the paper scale's contact radii,
# and the stiffer membrane with the idle arm parked) into fabric_stretch_<NAME>.{json,md,png}.
cd "$(dirname "$0")/../.."
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
MODEL=${MODEL:-models/pretrained/worldcontact-lift-handle}
R=/tmp/expand_speed; mkdir -p $R "${OUT:-$R/out}"
NAME=${NAME:-$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1 | grep -o 'H[0-9][0-9]*' | head -1 | tr H h)}
SETS=(--set sim.device=cuda --set validate.device=cuda --set expand.device=cuda --set sim.iterations=${ITERATIONS:-20}
  --set expand.batch_size=${SLOTS:-128} --set expand.slots.planner_workers=${PLANNERS:-8}
  --set expand.write_processes=${WRITERS:-1} --set sim.worlds=64 ${EXTRA:-})
case "$1" in
  start)
    cat /tmp/gpu/part-* | xz -dc -T0 | tar x -C / || exit 1
    mkdir -p ~/.cache/warp && xz -dc scripts/gpu/kernel_cache/warp-1.19.0_newton-1.8.0_sm90.tar.xz | tar x -C ~/.cache/warp --skip-old-files
    nvidia-smi --query-gpu=name,memory.used --format=csv
    python3 -m benchmarks.expand_smoke --device cuda --model $MODEL ${EXTRA:-} --slots ${SMOKE_SLOTS:-4,64,128,256} \
      --frames ${SMOKE_FRAMES:-40} --out $R/smoke.json || exit 1
    cp $R/smoke.json "$OUT"/ 2>/dev/null
    PARKED="scene.robot.left_base_xyz_yaw_deg=[-0.75, 0.0, 0.0, 0.0]"
    [ -n "${PROBE_SETTINGS+x}" ] || PROBE_SETTINGS=("scene.bag.target_vertices=300" "scene.bag.target_vertices=1200"
      "sim.bag.tri_ke=10000.0,sim.bag.tri_ka=10000.0,$PARKED" "scene.bag.target_vertices=2500"
      "scene.bag.target_vertices=5000,sim.bag.particle_radius_m=0.002,sim.self_contact_margin_m=0.0015,sim.self_contact_gap_m=0.001,tasks.common.closed_m=0.002")
    cat > $R/job.sh <<JOB
python3 -m benchmarks.expand_speed --params params.yaml ${SETS[*]@Q} --worlds ${WORLDS:-32,64,128} \\
  --model $MODEL --newton-seconds ${NEWTON_S:-45} --target ${TARGET:-150} --teacher-plans ${TEACHER:-64} --work $R/work \\
  --out $R/expand_speed_$NAME.json
[ "${PROBE_PLANS:-0}" -gt 0 ] && python3 -m benchmarks.fabric_stretch --params params.yaml --set sim.device=cuda \\
  --set validate.device=cuda --set sim.iterations=${ITERATIONS:-20} --set sim.worlds=${PROBE_PLANS:-0} \\
  --plans ${PROBE_PLANS:-0} --settings ${PROBE_SETTINGS[*]@Q} --out $R/fabric_stretch_$NAME.json
JOB
    setsid nohup bash $R/job.sh > $R/bench.log 2>&1 < /dev/null &
    echo $! > $R/bench.pid
    sleep ${FIRST_WAIT:-300}; tail -c 1500 $R/bench.log | tr '\r' '\n' | tail -15 ;;
  wait)
    end=$((SECONDS + ${WAIT:-540}))
    while kill -0 "$(cat $R/bench.pid)" 2>/dev/null && [ $SECONDS -lt $end ]; do sleep 5; done
    tail -c 3000 $R/bench.log | tr '\r' '\n' | grep -v "it/s\]$" | tail -30
    cp $R/expand_speed_$NAME.* $R/fabric_stretch_$NAME.* $R/work/expand.json "$OUT"/ 2>/dev/null; ls "$OUT" ;;
  *) echo "usage: $0 start|wait" >&2; exit 2 ;;
esac
