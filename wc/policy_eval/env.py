"""`WorldContactLiftEnv`: the policy task ("right grasp and lift") closed-loop in the Newton simulator.

reset(seed): trial seed s -> episode seed `policy_eval.seed_offset + s` (inside the policy seed stream of
wc.seeds, so never a simulate or expand episode seed); the task's coverage cell, speed and amplitude are drawn from
it, and its initial state is sampled, settled and planned exactly as the data-generation agent does
(wc.agent.runner.reset_batch). Frame 0 is the settled state with the robot at the planned start action.

step(action (7,)): right arm q_R (6, rad) + gripper opening d_R (m), the dataset's `action` format. The
14-D command keeps the left arm where the task program holds it; the kinematic robot moves from the
current command to the new one over one frame (`sim.substeps` solver steps), then both cameras render
the new state with the render stage's renderer, and each frame goes through the dataset's video encode and
decode (wc.policy.video_roundtrip), so the policy sees what it was trained on. Observations: pixels.top /
pixels.wrist (H, W, 3) uint8 RGB and agent_pos (7,) float32 = the commanded right arm (the dataset's observation.state).

Success (info["is_success"], reward 1, terminated): the bag's lowest vertex >= lift_height_m above the
table top at every frame for hold_s. Also terminated: a non-finite action or physics state; truncated: once the
hold can no longer complete by max_steps (null: the planned task program's length plus the hold), the same
verdict as stepping on to max_steps.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from wc.agent.runner import build_task_world, reset_batch
from wc.config import ParamsError, load_section, read_params
from wc.devices import resolve_warp_device
from wc.dynamics import ObjectState
from wc.policy.dataset import RIGHT_ARM, fps_of
from wc.policy.dataset_config import DatasetConfig
from wc.policy.policy_config import PolicyConfig
from wc.policy_eval.config import POLICY_SEEDS, PolicyEvalConfig
from wc.policy_eval.stepper import FrameStepper
from wc.policy_eval.success import TrialJudge, hold_frames
from wc.policy.video_roundtrip import VideoRoundTrip
from wc.render.config import RenderConfig
from wc.render.geometry import scene_geometry
from wc.render.renderer import EpisodeRenderer
from wc.render.rig import render_cameras
from wc.scene.config import SceneConfig
from wc.scene.scene import Scene
from wc.sim.config import SimConfig
from wc.tasks.bag_geometry import lowest_height
from wc.tasks.base import EpisodeSpec, Task, get_task

MAX_PLANS = 8  # draws of (cell, speed, amplitude) per reset before an unplannable initial state is an error


def sample_spec(task: Task, episode_seed: int, attempt: int = 0) -> EpisodeSpec:
    """The episode's coverage cell, speed and amplitude, uniform over the task's cells and ranges."""
    rng = np.random.default_rng([episode_seed, attempt])
    cell = int(rng.integers(task.num_cells()))
    speed, amplitude = (float(rng.uniform(*r)) for r in (task.speed_range(), task.amplitude_range()))
    return EpisodeSpec(task.name, episode_seed, cell, speed, amplitude)


def build_renderer(params: dict[str, Any], scene: Scene, device: str, batch: int) -> EpisodeRenderer:
    """The render stage's renderer of the `render.cameras` views of `scene`, `batch` frames per call."""
    scene_cfg, render_cfg = load_section(params, "scene", SceneConfig), load_section(params, "render", RenderConfig)
    try:
        cameras = render_cameras(scene_cfg.cameras, render_cfg.cameras, render_cfg.width, render_cfg.height)
    except ValueError as err:
        raise ParamsError(f"{params.get('_source', '<params>')}: {err}") from err
    return EpisodeRenderer(scene_geometry(scene), cameras, device, batch, render_cfg.shadows)


def side_by_side(observation: dict[str, Any]) -> np.ndarray:
    """An observation's camera views side by side, (H, W * cameras, 3) uint8: a video frame."""
    return np.concatenate(list(observation["pixels"].values()), axis=1)


def trial_info(judge: TrialJudge, success: bool, height_m: float, trial_seed: int, episode_seed: int) -> dict[str, Any]:
    """The info dict of a trial's step (reset: frame 0)."""
    return {"is_success": bool(success), "lowest_height_m": height_m, "max_lift_m": judge.monitor.max_height_m,
            "steps": judge.steps, "failure": judge.failure or "", "trial_seed": trial_seed,
            "episode_seed": episode_seed}


class WorldContactLiftEnv(gym.Env):
    """The lift task closed-loop (see the module docstring). `params`: a params dict or YAML path
    (sections policy_eval, policy, scene, sim, render, tasks); `overrides`: `key.sub=value` strings."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(self, params: dict[str, Any] | str | Path = "params.yaml", overrides: list[str] | None = None,
                 render_mode: str | None = "rgb_array") -> None:
        if not isinstance(params, dict):
            params = read_params(params, overrides)
        elif overrides:
            raise ValueError("overrides apply to a params file; edit the params dict instead")
        self.cfg = load_section(params, "policy_eval", PolicyEvalConfig)
        self.device = resolve_warp_device(self.cfg.device, "policy_eval.device")
        sim_cfg = dataclasses.replace(load_section(params, "sim", SimConfig), worlds=1, device=self.device)
        scene_cfg = load_section(params, "scene", SceneConfig)
        render_cfg = load_section(params, "render", RenderConfig)
        self.params = params  # what a batched env over the same trials is built from (wc.policy_eval.batched_env)
        self.instruction = load_section(params, "policy", PolicyConfig).task
        self.task = get_task(self.cfg.task, params)
        self.world = build_task_world(scene_cfg, sim_cfg, self.task)
        if self.world.free_sim is not None:
            raise ParamsError(f"policy_eval.task {self.cfg.task!r} hands objects off between simulators; "
                              "closed-loop evaluation supports tasks simulated in one")
        self.scene = self.world.scene
        self.stepper = FrameStepper(self.world.sim)
        self.frame_dt_s = sim_cfg.frame_dt_s
        self.hold = hold_frames(self.cfg.hold_s, self.frame_dt_s)
        self.renderer = build_renderer(params, self.scene, self.device, 1)
        self.video = VideoRoundTrip(load_section(params, "dataset", DatasetConfig), fps_of(sim_cfg.frame_dt_s))
        self.cameras = list(self.renderer.cameras)
        self.metadata = {**self.metadata, "render_fps": fps_of(self.frame_dt_s)}
        self.render_mode = render_mode
        image = gym.spaces.Box(0, 255, (render_cfg.height, render_cfg.width, 3), np.uint8)
        self.observation_space = gym.spaces.Dict({
            "pixels": gym.spaces.Dict({name: image for name in self.cameras}),
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, (7,), np.float32)})
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (7,), np.float32)
        self._max_episode_steps = self.cfg.max_steps or 0  # read by lerobot's rollout after reset
        self.seconds = {"reset": 0.0, "physics": 0.0, "render": 0.0}
        self._trial_seed: int | None = None
        self._resets: dict[int, tuple[EpisodeSpec, ObjectState, np.ndarray]] = {}  # trial seed -> planned reset:
        # every policy starts a trial from the very same settled state, and pays for settling it once
        self._obs: dict[str, Any] | None = None
        self.judge: TrialJudge | None = None  # the current trial's verdict

    # lerobot's rollout asks the sub-environments for these
    @property
    def task_description(self) -> str:
        return self.instruction

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        if seed is None:  # no seed: the trial after the previous one
            seed = 0 if self._trial_seed is None else self._trial_seed + 1
        if seed < 0:
            raise ValueError(f"trial seed must be >= 0, got {seed}")
        self._trial_seed = int(seed)
        self.episode_seed = self.cfg.seed_offset + self._trial_seed
        self.episode_spec, state, self.planned_actions = self.planned_reset(self._trial_seed)
        self.stepper.start(state, self.planned_actions[0])
        self._left = self.planned_actions[0, :RIGHT_ARM.start].copy()
        self.judge = self.new_judge(self.planned_actions)
        self._max_episode_steps = self.judge.max_steps
        height = self.lowest_heights(state.x[None])[0]
        success = self.judge.start(height)  # frame 0 counts: the bag rests on the table there
        self.x = state.x  # (N, 3) object vertices of the current frame [m]
        self._obs = self._observe(state.x, self.planned_actions[0])
        return self._obs, self._info(success, height)

    def planned_reset(self, trial_seed: int) -> tuple[EpisodeSpec, ObjectState, np.ndarray]:
        """Trial `trial_seed`'s spec, settled frame-0 state and planned actions (T, 14), planned once per seed."""
        episode_seed = self.cfg.seed_offset + trial_seed
        if episode_seed not in POLICY_SEEDS:
            raise ValueError(f"trial seed {trial_seed}: episode seed {episode_seed} leaves the policy seed stream "
                             f"[{POLICY_SEEDS.start}, {POLICY_SEEDS.stop})")
        if trial_seed not in self._resets:
            tic = time.perf_counter()
            self._resets[trial_seed] = self._plan(episode_seed)
            self.seconds["reset"] += time.perf_counter() - tic
        return self._resets[trial_seed]

    def new_judge(self, planned_actions: np.ndarray) -> TrialJudge:
        """The verdict of a trial with this plan: max_steps, null = the program's length plus the hold."""
        max_steps = self.cfg.max_steps or (len(planned_actions) - 1 + self.hold)
        return TrialJudge(self.cfg.lift_height_m, self.hold, max_steps)

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        if self.judge is None or self.judge.done:
            raise RuntimeError("step() after the episode ended: call reset() first")
        action = np.asarray(action, np.float32)
        if action.shape not in ((7,), (1, 7)):
            raise ValueError(f"action must be (7,): right arm q_R (6, rad) + gripper opening (m), got {action.shape}")
        command = np.concatenate([self._left, action.reshape(7)])
        height, failure = float("nan"), None
        if not np.isfinite(command).all():
            failure = "non_finite_action"
        else:
            tic = time.perf_counter()
            x, v = self.stepper.advance(command)
            self.seconds["physics"] += time.perf_counter() - tic
            if not (np.isfinite(x).all() and np.isfinite(v).all()):
                failure = "non_finite"
            else:
                self.x = x
                height = self.lowest_heights(x[None])[0]
                self._obs = self._observe(x, command)
        success, terminated, truncated = self.judge.step(height, failure)
        return self._obs, float(success), terminated, truncated, self._info(success, height)

    def _plan(self, episode_seed: int) -> tuple[EpisodeSpec, ObjectState, np.ndarray]:
        """Sample, settle and plan an episode as the agent does: (spec, frame-0 state, planned actions (T, 14),
        the task's own program, i.e. the oracle); another draw of the spec if one cannot be planned."""
        for attempt in range(MAX_PLANS):
            spec = sample_spec(self.task, episode_seed, attempt)
            runnable, _ = reset_batch(self.world, [spec])
            if runnable:
                return runnable[0]
        raise RuntimeError(f"{self.task.name}: no plannable episode for episode seed {episode_seed} "
                           f"in {MAX_PLANS} draws")

    def render(self) -> np.ndarray:
        """The current views side by side, (H, W * cameras, 3) uint8."""
        if self._obs is None:
            raise RuntimeError("render() before reset()")
        return side_by_side(self._obs)

    def lowest_heights(self, x: np.ndarray) -> list[float]:
        """The bag's lowest vertex above the table top [m] per state of x (B, N, 3)."""
        return [float(h) for h in lowest_height(self.scene, x)]

    def raw_frames(self, x: np.ndarray, command: np.ndarray) -> dict[str, np.ndarray]:
        """Each camera's render (H, W, 3) of state x under the robot command, before the video round trip."""
        frames = self.renderer.render(x[None], self.scene.link_poses(command)[None], "policy_eval")
        return {n: frames[n][0] for n in self.cameras}

    def _observe(self, x: np.ndarray, command: np.ndarray) -> dict[str, Any]:
        tic = time.perf_counter()
        observation = self.observation(self.raw_frames(x, command), command)
        self.seconds["render"] += time.perf_counter() - tic
        return observation

    def observation(self, frames: dict[str, np.ndarray], command: np.ndarray) -> dict[str, Any]:
        """The policy's observation of raw camera frames (H, W, 3) under the robot command (14,): each frame as the
        dataset stored it (the video round trip), agent_pos the commanded right arm."""
        return {"pixels": {n: self.video(frames[n]) for n in self.cameras},
                "agent_pos": np.asarray(command[RIGHT_ARM], np.float32)}

    def _info(self, success: bool, height: float) -> dict[str, Any]:
        return trial_info(self.judge, success, height, self._trial_seed, self.episode_seed)
