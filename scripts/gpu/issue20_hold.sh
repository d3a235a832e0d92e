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
source scripts/gpu/hold_lib.sh
case "$1" in
  unpack) unpack_wheels "import warp, newton, zarr, lerobot, av, datasets, draccus; from lerobot.policies.act.modeling_act import ACTPolicy; print('imports ok', warp.__version__, newton.__version__, lerobot.__version__)" ;;
  data)
    background scripts/gpu/issue20_data.sh
    wait_bg ${2:-540} $R/*.json $R/sheet_*.png $R/policy_success.* ;;
  policies)
    cat /tmp/gpu_data/lerobot.tar.* | tar x -C $R || exit 1
    du -sh $R/lerobot/*
    rm -f $R/steps.log
    background scripts/gpu/issue20_policies.sh
    wait_bg ${2:-540} $R/*.json $R/sheet_*.png $R/policy_success.* ;;
  wait) wait_bg ${2:-540} $R/*.json $R/sheet_*.png $R/policy_success.* ;;
  pack)
    tar cf - -C $R lerobot | split -b 15000000 -d - "$OUT"/lerobot.tar.
    ls -la "$OUT" ;;
  *) echo "usage: $0 unpack | data [S] | wait S | pack | policies [S]" >&2; exit 2 ;;
esac
