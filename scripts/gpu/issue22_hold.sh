#!/bin/bash
# Issue 22 (Table 1 on the GPU) in two holds, as calls of at most 10 minutes. Needs the packed wheels (warp, newton,
# zarr, trimesh and their deps; .gpu/p00..p02) copied to /tmp/gpu, one part per call, before `unpack`.
#   issue22_hold.sh unpack      the wheels into /tmp/site, the precompiled CUDA kernels into ~/.cache/warp
#   issue22_hold.sh train [S]   hold 1: issue22_train.sh in the background (data, then every learned method side by
#                               side under one wall-clock budget); waits like `wait`
#   issue22_hold.sh baselines [S]  as train, the three baselines only (alone on the GPU); P=params file
#   issue22_hold.sh models      hold 1: the trained models as one tar piece per method to $OUT
#   issue22_hold.sh eval [S]    hold 2: carried model pieces (/tmp/gpu_models) into models/table1, then
#                               issue22_eval.sh in the background (fresh test episodes, evaluate, speed); waits
#   issue22_hold.sh wait S      wait up to S seconds for the background job; progress; reports to $OUT
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
case "$1" in
  unpack) unpack_wheels "import warp, newton, zarr, trimesh; print('imports ok', warp.__version__, newton.__version__, zarr.__version__)" ;;
  train) background scripts/gpu/issue22_train.sh; wait_bg ${2:-540} $R/*.json $R/*.csv $R/*.png $R/*.md ;;
  baselines) export ONLY=baselines; background scripts/gpu/issue22_train.sh; wait_bg ${2:-540} $R/*.json ;;
  models)
    for d in $R/models/*/ $R/models/ablations/*/ $R/models/baselines/*/; do
      [ -f "$d/model.safetensors" ] && tar cf "$OUT/model_$(basename $d).tar" -C "$d" . ; done
    ls -la "$OUT" ;;
  eval)  # models/table1 carried as it is, or the pieces in /tmp/gpu_models
    mkdir -p models/table1/ablations models/table1/baselines
    for t in $(ls /tmp/gpu_models/model_*.tar 2>/dev/null); do
      name=$(basename $t .tar); name=${name#model_}
      case $name in worldcontact) dir=models/table1/worldcontact ;;
        no_*) dir=models/table1/ablations/$name ;; *) dir=models/table1/baselines/$name ;; esac
      mkdir -p $dir && tar xf $t -C $dir && echo "$dir: $(ls $dir | tr '\n' ' ')"
    done
    rm -f $R/steps.log; background scripts/gpu/issue22_eval.sh; wait_bg ${2:-500} $R/*.json $R/*.csv $R/*.png $R/*.md ;;
  wait) wait_bg ${2:-540} $R/*.json $R/*.csv $R/*.png $R/*.md ;;
  *) echo "usage: $0 unpack | train [S] | baselines [S] | models | eval [S] | wait S" >&2; exit 2 ;;
esac
