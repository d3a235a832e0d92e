#!/bin/bash
# What closes the teacher check's gap, on one fresh Newton lift_handle set on one GPU. Three fine-tunes of
# STAGE1 (the contact-task model before any lift fine-tune), side by side on the GPU, the same learning rates:
#   w5         window 5, batch 8, the slipped-strap lifts kept for training (the shipped model's recipe, more data)
#   w10        window 10, batch 4 (the same frames per step, twice the horizon; fewer steps for the same GPU time)
#   w5nofail   window 5, batch 8, accepted lifts only (the "without the failed lifts" ablation)
# then each of them and the shipped model: one batch of generated episodes, the teacher check of up to TEACHER plans
# per verdict, and 100-frame rollouts of the held-out test episodes against constant velocity. Run in the background
# (hold_lib.sh `background`) once the packages are in place; progress in /tmp/run/steps.log, reports in /tmp/run/out.
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
STAGE1=${STAGE1:-/tmp/stage1}
SHIPPED=models/pretrained/worldcontact-lift-handle
fresh_lift_data ${EPISODES:-128} ${ATTEMPTS:-256} ${SIM_MINUTES:-4} 4 8
source scripts/gpu/gpu_overrides.sh
python -m stages.validate --params params.yaml "${VAL_SETS[@]}" --set validate.device=cuda \
  --set validate.train_on_task_failures=false --raw $R/raw.zarr --out $R/store_nofail.zarr \
  --report $OUT/validate_nofail.json > $R/validate_nofail.log 2>&1 &
validating=$!

# the shipped model's expansion, teacher check and held-out rollouts while the fine-tunes train
chain shipped $SHIPPED &
wait $validating  # the accepted-only store
step "validate nofail: $(tail -c 200 $R/validate_nofail.log | tr '\r\n' '  ')"

train() {  # train TAG STORE WINDOW BATCH BASE PROJ
  STORE=$2 CKPT_OUT=$R/train_$1 WORK=$R/model_$1 MAX_MINUTES=${TRAIN_MINUTES:-7.5} INIT_FROM=$STAGE1 BATCH=$4 \
    BASE_STEPS=$5 PROJ_STEPS=$6 PEAK_LR=3.0e-5 BASE_WARMUP=500 \
    EXTRA_TRAIN_SETS="--set train.fine_tune_lr_scale=1.0 --set train.window=$3 --set train.eval_every_steps=1000" \
    bash scripts/gpu/world_model_chunk.sh > $R/train_$1.log 2>&1
  step "train $1 rc=$? $(tail -c 300 $R/train_$1.log | tr '\r\n' '  ')"
}
train w5 $R/store.zarr 5 8 3000 1000 & t1=$!
train w10 $R/store.zarr 10 4 ${W10_BASE:-1600} ${W10_PROJ:-500} & t2=$!
train w5nofail $R/store_nofail.zarr 5 8 3000 1000 & t3=$!
wait $t1 $t2 $t3
for tag in w5 w10 w5nofail; do
  model=$(latest_model $R/model_$tag); [ "$model" = $R/model_$tag ] || step "$tag: partial model"
  chain $tag $model &
done
wait
step "DONE"
