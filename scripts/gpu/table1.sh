#!/bin/bash
# Table 1 on one GPU, on two machines one after the other, as commands of at most 10 minutes each. Needs the packed wheels (warp, newton,
# zarr, trimesh and their deps; .gpu/p00..p02) copied to /tmp/gpu, one part per call, before `unpack`.
#   table1.sh unpack      the wheels into /tmp/site, the precompiled CUDA kernels into ~/.cache/warp
#   table1.sh train [S]   first machine: table1_train.sh in the background (data, then every learned method side by
#                               side under one wall-clock budget); waits like `wait`
#   table1.sh baselines [S]  as train, the three baselines only (alone on the GPU); P=params file
#   table1.sh models      first machine: the trained models as one tar piece per method to $OUT
#   table1.sh eval [S]    second machine: carried model pieces (/tmp/gpu_models) into models/table1, then
#                               table1_eval.sh in the background (fresh test episodes, evaluate, speed); waits
#   table1.sh wait S      wait up to S seconds for the background job; progress; reports to $OUT
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
case "$1" in
  unpack) unpack_wheels "import warp, newton, zarr, trimesh; print('imports ok', warp.__version__, newton.__version__, zarr.__version__)" ;;
  train) background scripts/gpu/table1_train.sh; wait_bg ${2:-540} $R/*.json $R/*.csv $R/*.png $R/*.md ;;
  baselines) export ONLY=baselines; background scripts/gpu/table1_train.sh; wait_bg ${2:-540} $R/*.json ;;
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
    rm -f $R/steps.log; background scripts/gpu/table1_eval.sh; wait_bg ${2:-500} $R/*.json $R/*.csv $R/*.png $R/*.md ;;
  wait) wait_bg ${2:-540} $R/*.json $R/*.csv $R/*.png $R/*.md ;;
  *) echo "usage: $0 unpack | train [S] | baselines [S] | models | eval [S] | wait S" >&2; exit 2 ;;
esac
