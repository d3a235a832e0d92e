# The stage overrides of the lift_handle world-model runs on one GPU (sourced by world_model.sh, contact_tasks_data.sh,
# world_model_chunk.sh, expand_check_rollouts.sh and the runs built on them): the CPU default scene (306-vertex bag)
# simulated with Newton on the GPU, and params/gpu.yaml's training recipe (learning rates, noise, events, per-axis scales, held-out
# rollout selection) on the static compiled path, its schedule scaled to 14,000 base + 4,000 projection steps
# (what 30 minutes of one GPU fit after the simulation).
# Packed wheels (warp, newton, zarr, trimesh) on PYTHONPATH; state lives in /tmp/run. The acceptance checks run on the
# GPU too (validate.device): on the host they cost more than the simulation (reports/check_cost_cpu.md). No
# torch.compile by default: it recompiled for every layout of multi-task data (~250 s a step on the H100).
# SIM_ITERATIONS: Newton's VBD iterations per substep for the data and the teacher check (params.yaml's 5 by default;
# reports/gpu/newton_convergence_h100.md: at 5 about half the lifts slip out of the pads, at 10 and more none do)
# SCENE: key=value overrides (space-separated) of the scene and its simulation for every stage of a run (a finer bag
# and its step: the stores' meshes must match the scene each stage builds), e.g.
# SCENE="scene.bag.target_vertices=1200 sim.dt_s=0.001 sim.substeps=40"
SCENE_SETS=(); for kv in ${SCENE:-}; do SCENE_SETS+=(--set "$kv"); done
SIM_SETS=("${SCENE_SETS[@]}" --set sim.device=cuda --set validate.device=cuda --set sim.worlds=${WORLDS:-32} --set agent.workers=${WORKERS:-1}
  --set sim.iterations=${SIM_ITERATIONS:-5}
  --set "agent.tasks=${TASKS:-[lift_handle, grasp_handle, shake, lift_two_arms, place, release_drop]}"
  --set agent.episodes_per_task=${EPISODES:-29} --set agent.max_attempts_per_task=${ATTEMPTS:-96})
VAL_SETS=("${SCENE_SETS[@]}" --set validate.val_per_task=${VAL_PER_TASK:-2} --set validate.test_per_task=${TEST_PER_TASK:-2} --set validate.train_on_task_failures=${TASK_FAILURES:-true})
TRAIN_SETS=("${SCENE_SETS[@]}"
  --set "train.base={steps: ${BASE_STEPS:-14000}, peak_lr: ${PEAK_LR:-1.0e-4}, start_lr: 1.0e-6, final_lr: 5.0e-6, warmup_steps: ${BASE_WARMUP:-2000}}"
  --set "train.projection={steps: ${PROJ_STEPS:-4000}, peak_lr: 2.0e-5, start_lr: 2.0e-7, final_lr: 5.0e-6, warmup_steps: 500}"
  --set train.batch_size=${BATCH:-8} --set train.input_noise_m=3.0e-4 --set train.eval_every_steps=2000
  --set train.val_windows=64 --set train.rollout_frames=60 --set train.select_by=rollout --set train.event_oversample=3.0
  --set train.per_axis_scales=true --set train.checkpoint_every_steps=1000 --set train.autocast_bf16=true
  --set train.tf32=true --set train.static=true --set train.compile=${COMPILE:-false} --set train.cuda_graph=true
  --set train.device=cuda --set "train.init_from='${INIT_FROM:-}'" ${EXTRA_TRAIN_SETS:-})
# the expansion and teacher check on the GPU (expand_check_rollouts.sh)
EXP_SETS=("${SCENE_SETS[@]}" --set expand.target_trajectories=${TARGET:-150} --set expand.max_minutes=${EXPAND_MINUTES:-3.5} --set expand.max_attempts=${ATTEMPTS_EXPAND:-600}
  --set expand.batch_size=${EXPAND_BATCH:-64} --set expand.device=cuda --set validate.device=cuda --set sim.device=cuda
  --set sim.worlds=32 --set sim.iterations=${SIM_ITERATIONS:-5} --set expand.pad_carry=${PAD_CARRY:-false} --set expand.untangle=${UNTANGLE:-bounded+rollback}
  --set expand.self_contact=${SELF_CONTACT:-false} --set expand.untangle_share=${SHARE:-0.8} ${EXTRA_EXP_SETS:-})
mkdir -p /tmp/run
