#!/bin/bash
# Issue 20 on one GPU: the policy comparison's data (hold 1) and its three policies (hold 2), as calls of at most
# 10 minutes. Needs the packed wheels (warp, newton, zarr, trimesh, lerobot and its dataset deps) in /tmp/gpu.
#   issue20_hold.sh unpack      the wheels into /tmp/site, the precompiled CUDA kernels into ~/.cache/warp
#   issue20_hold.sh data        issue20_data.sh in the background (outlives the call); waits like `wait`
#   issue20_hold.sh wait S      wait up to S seconds for the background job; progress; reports to $OUT
#   issue20_hold.sh pack        /tmp/run/lerobot as 15 MB pieces to $OUT (the datasets travel to the next hold)
#   issue20_hold.sh policies    the carried dataset pieces (/tmp/gpu_data) unpacked to /tmp/run/lerobot, then
#                               issue20_policies.sh in the background; waits like `wait`
cd "$(dirname "$0")/../.."
export PYTHONPATH=/tmp/site:$PWD
R=/tmp/run; mkdir -p $R "$OUT"
wait_bg() {
  end=$((SECONDS + ${1:-500}))
  while kill -0 "$(cat $R/bg.pid)" 2>/dev/null && [ $SECONDS -lt $end ]; do sleep 5; done
  cat $R/steps.log; tail -c 600 $R/bg.log
  for f in $R/*.json $R/sheet_*.png $R/policy_success.*; do [ -f "$f" ] && cp "$f" "$OUT"/; done
  ls "$OUT" | head -20
}
case "$1" in
  unpack)
    cat /tmp/gpu/part-* | xz -dc -T0 | tar x -C / || exit 1
    mkdir -p ~/.cache/warp && xz -dc scripts/gpu/kernel_cache/warp-1.19.0_newton-1.8.0_sm90.tar.xz | tar x -C ~/.cache/warp --skip-old-files
    python -c "import warp, newton, zarr, lerobot, av, datasets, draccus; from lerobot.policies.act.modeling_act import ACTPolicy; print('imports ok', warp.__version__, newton.__version__, lerobot.__version__)"
    nvidia-smi --query-gpu=name,memory.used --format=csv ;;
  data)
    setsid nohup bash scripts/gpu/issue20_data.sh > $R/bg.log 2>&1 < /dev/null &
    echo $! > $R/bg.pid
    wait_bg ${2:-540} ;;
  policies)
    cat /tmp/gpu_data/lerobot.tar.* | tar x -C $R || exit 1
    du -sh $R/lerobot/*
    rm -f $R/steps.log
    setsid nohup bash scripts/gpu/issue20_policies.sh > $R/bg.log 2>&1 < /dev/null &
    echo $! > $R/bg.pid
    wait_bg ${2:-540} ;;
  wait) wait_bg ${2:-540} ;;
  pack)
    tar cf - -C $R lerobot | split -b 15000000 -d - "$OUT"/lerobot.tar.
    ls -la "$OUT" ;;
  *) echo "usage: $0 unpack | data [S] | wait S | pack | policies [S]" >&2; exit 2 ;;
esac
