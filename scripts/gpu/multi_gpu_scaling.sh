#!/bin/bash
# World-model training and data generation across the GPUs of one host (benchmarks/train_scaling.py,
# benchmarks/generate_scaling.py) on a bare multi-GPU machine, as device calls of at most 10 minutes:
#   bash scripts/gpu/multi_gpu_scaling.sh start     the packed wheels (/tmp/gpu/part-*) and Newton's kernel cache
#                                                   unpacked, then in the background: fresh lift_handle data (Newton at
#                                                   20 VBD iterations, validated), train_scaling on it, generate_scaling,
#                                                   policy_placement (ACT on the carried data/lerobot datasets)
#   bash scripts/gpu/multi_gpu_scaling.sh wait [S]  wait up to S seconds (default 540); progress and reports to $OUT
#   bash scripts/gpu/multi_gpu_scaling.sh logs      the job's logs to $OUT
#   bash scripts/gpu/multi_gpu_scaling.sh stop      end the background job
# The job writes its reports to $R/reports (a device call's $OUT is emptied at the next call); `wait` copies them.
# Settings: TRAIN_PROCS (K for training, default 1,2,4 up to the GPUs), SAMPLES (training samples per K, 19200),
# GEN_DEVICES (K for simulate and expand, default 1,2), GEN_EPISODES (episodes per stage and K, 128: 4 batches of 32
# worlds), REPEAT_FIRST (non-empty: generate at the first K twice, the stages' own repeatability as a control),
# POLICY_STEPS (ACT steps per arm, 300), NAME (report tag, default e.g. h200x4). NCCL's NVLink multicast stays off
# (benchmarks/train_scaling.py). WC_DETERMINISTIC=run_to_run before `start`: fixed-order atomics in every process
# (wc/determinism.py); its kernels are not in the precompiled cache (expect minutes of compilation first).
cd "$(dirname "$0")/../.."
source scripts/gpu/hold_lib.sh
GPUS=$(nvidia-smi -L | wc -l)
NAME=${NAME:-$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1 | grep -o 'H[0-9]*' | tr H h)x$GPUS}
PROCS=${TRAIN_PROCS:-$(for k in 1 2 4 8; do [ $k -le $GPUS ] && echo -n "$k,"; done | sed 's/,$//')}
SIM=(--set sim.device=cuda --set validate.device=cuda --set sim.iterations=20 --set sim.worlds=64)
TRAIN=(--set train.base.peak_lr=1.0e-4 --set train.base.start_lr=1.0e-6 --set train.base.final_lr=5.0e-6
  --set train.input_noise_m=3.0e-4 --set train.event_oversample=3.0 --set train.per_axis_scales=true
  --set train.val_windows=64 --set train.autocast_bf16=true --set train.tf32=true --set train.cuda_graph=true
  --set "train.init_from=''")
job() {
  mkdir -p $R/reports
  step "data start ($GPUS GPUs: $(nvidia-smi --query-gpu=name --format=csv,noheader | head -1))"
  python3 -m stages.simulate "${SIM[@]}" --set "agent.tasks=[lift_handle]" --set agent.episodes_per_task=40 \
    --set agent.max_attempts_per_task=64 --set agent.workers=1 --out $R/raw.zarr --report $R/simulate.json \
    --memory '' > $R/data.log 2>&1 &&
  python3 -m stages.validate "${SIM[@]}" --set validate.val_per_task=4 --set validate.test_per_task=0 \
    --raw $R/raw.zarr --out $R/store.zarr --report $R/validate.json >> $R/data.log 2>&1
  step "data rc=$? $(tail -c 300 $R/data.log | tr '\r\n' '  ')"
  python3 -m benchmarks.train_scaling --params params.yaml "${TRAIN[@]}" --store $R/store.zarr --procs $PROCS \
    --samples ${SAMPLES:-19200} --timeout 600 --tag $NAME --out-dir $R/reports > $R/train_scaling.log 2>&1
  step "train_scaling rc=$? $(tail -c 600 $R/train_scaling.log | tr '\r\n' '  ')"
  python3 -m benchmarks.generate_scaling --params params.yaml "${SIM[@]}" --set sim.worlds=32 --set expand.device=cuda \
    --set expand.batch_size=128 --set expand.slots.planner_workers=6 --devices ${GEN_DEVICES:-1,2} \
    --episodes ${GEN_EPISODES:-128} --store $R/store.zarr --model models/pretrained/worldcontact-lift-handle \
    ${REPEAT_FIRST:+--repeat-first} --tag $NAME --out-dir $R/reports > $R/generate_scaling.log 2>&1
  step "generate_scaling rc=$? $(tail -c 600 $R/generate_scaling.log | tr '\r\n' '  ')"
  python3 -m benchmarks.policy_placement --params params.yaml --policy params/policy_act_gpu.yaml \
    --set policy.steps=${POLICY_STEPS:-300} --set policy.decay_steps=${POLICY_STEPS:-300} --data-root $R/lerobot \
    --tag $NAME --out-dir $R/reports > $R/policy_placement.log 2>&1
  step "policy_placement rc=$? $(tail -c 600 $R/policy_placement.log | tr '\r\n' '  ')"
}
case "$1" in
  start)
    unpack_wheels "import warp, newton, zarr, torch, lerobot; print(torch.cuda.device_count(), 'GPUs')"
    cp -a data/lerobot $R/lerobot || exit 1
    echo "cd $PWD && bash scripts/gpu/multi_gpu_scaling.sh job" > $R/job.sh
    background $R/job.sh
    sleep ${FIRST_WAIT:-60}; cat $R/steps.log ;;
  job) job ;;
  wait) wait_bg "${2:-540}"
    cp $R/steps.log $R/reports/* "$OUT"/ 2>/dev/null; ls "$OUT" ;;
  logs) cp $R/*.log $R/simulate.json $R/validate.json "$OUT"/; ls "$OUT" ;;
  stop) kill -- -"$(cat $R/bg.pid)" ;;
  *) echo "usage: $0 start | wait [SECONDS] | logs | stop" >&2; exit 2 ;;
esac
