#!/bin/bash
# The three-arm policy comparison on one GPU: its data (first machine) and its three policies (second machine), as
# commands of at most 10 minutes each. Needs the packed wheels (warp, newton, zarr, trimesh, lerobot and its dataset deps) in /tmp/gpu.
#   policy_comparison.sh unpack      the wheels into /tmp/site, the precompiled CUDA kernels into ~/.cache/warp
#   policy_comparison.sh data        policy_comparison_data.sh in the background (outlives the call); waits like `wait`
#   policy_comparison.sh wait S      wait up to S seconds for the background job; progress; reports to $OUT
#   policy_comparison.sh pack        /tmp/run/lerobot as 15 MB pieces to $OUT (the datasets travel to the next machine)
#   policy_comparison.sh policies    the carried dataset pieces (/tmp/gpu_data) unpacked to /tmp/run/lerobot, then
#                               policy_comparison_policies.sh in the background; waits like `wait`
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
case "$1" in
  unpack) unpack_wheels "import warp, newton, zarr, lerobot, av, datasets, draccus; from lerobot.policies.act.modeling_act import ACTPolicy; print('imports ok', warp.__version__, newton.__version__, lerobot.__version__)" ;;
  data)
    background scripts/gpu/policy_comparison_data.sh
    wait_bg ${2:-540} $R/*.json $R/sheet_*.png $R/policy_success.* ;;
  policies)
    cat /tmp/gpu_data/lerobot.tar.* | tar x -C $R || exit 1
    du -sh $R/lerobot/*
    rm -f $R/steps.log
    background scripts/gpu/policy_comparison_policies.sh
    wait_bg ${2:-540} $R/*.json $R/sheet_*.png $R/policy_success.* ;;
  wait) wait_bg ${2:-540} $R/*.json $R/sheet_*.png $R/policy_success.* ;;
  pack)
    tar cf - -C $R lerobot | split -b 15000000 -d - "$OUT"/lerobot.tar.
    ls -la "$OUT" ;;
  *) echo "usage: $0 unpack | data [S] | wait S | pack | policies [S]" >&2; exit 2 ;;
esac
