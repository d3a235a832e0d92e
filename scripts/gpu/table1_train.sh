#!/bin/bash
# Table 1, first machine (run in the background by table1.sh train; progress in /tmp/run/steps.log):
#   1. Newton: the six contact tasks of the shipped model's data (params/gpu_table1.yaml: fresh seeds), validated with
#      2 val + 2 test whole episodes per task -> /tmp/run/store.zarr
#   2. every learned method on its train split, side by side on the one GPU, under one wall-clock budget: WorldContact
#      from scratch and both ablations (train stage, the same recipe and steps), RoboCraft, RoboCook and AdaptiGraph
#      (train_baselines, until the budget or the convergence of their validation loss)
# ONLY=baselines trains the three baselines alone, without the WorldContact trainings beside them; P names the params.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
P=${P:-params/gpu_table1.yaml}; mkdir -p $R/models/ablations $R/models/baselines
step "simulate start"
python -m stages.simulate --params $P --out $R/raw.zarr --report $R/simulate.json --memory $R/memory.json \
  > $R/simulate.log 2>&1
step "simulate rc=$? overflow lines $(grep -c overflowed $R/simulate.log) $(tail -c 300 $R/simulate.log | tr '\r\n' '  ')"
python -m stages.validate --params $P --raw $R/raw.zarr --out $R/store.zarr --report $R/validate.json > $R/validate.log 2>&1
step "validate rc=$? $(tr "\r" "\n" < $R/validate.log | tail -1)"
train() {  # name, out, extra --set
  python -m stages.train --params $P "${@:3}" --store $R/store.zarr --out $2 --report $R/train_$1.json \
    --curves $R/train_loss_$1.csv > $R/train_$1.log 2>&1
  step "train $1 rc=$? $(tail -c 300 $R/train_$1.log | tr '\r\n' '  ')"
}
if [ "${ONLY:-}" != baselines ]; then
  train worldcontact $R/models/worldcontact &
  train no_contact_tokenizer $R/models/ablations/no_contact_tokenizer --set model.tokenizer=linear &
  train no_hierarchical_compression $R/models/ablations/no_hierarchical_compression --set model.compress=false &
fi
for b in robocraft robocook adaptigraph; do
  ( python -m stages.train_baselines --params $P --set "baselines.names=[$b]" --store $R/store.zarr \
      --out $R/models/baselines --report $R/train_baseline_$b.json > $R/train_baseline_$b.log 2>&1
    step "baseline $b rc=$? $(tail -c 300 $R/train_baseline_$b.log | tr '\r\n' '  ')" ) &
done
step "trainings started"
wait
step "DONE"
