"""The Newton source simulator as an evaluated method, at its reference setting or a cheaper one.

Each held-out case is re-simulated from its first stored frame (cloth vertices x, v as stored; rigid objects
posed from their stored vertices, as NewtonSimulator writes any state) under the case's recorded 14-D actions,
in the case's own collision scene (held objects included), and answered in the store's vertex order, so the
evaluate metrics apply unchanged. Settings (params `evaluate.methods`, kind `newton`):

    iterations            VBD iterations per solver step (params sim.iterations)
    substeps              solver steps per frame; the solver dt is frame dt / substeps, the frame dt stays
    cloth_vertices_scale  every cloth mesh rebuilt at this x its target_vertices; the stored frame-0 state is
                          mapped onto the coarse mesh and the result back (wc.scene.resample, rest space)

`NewtonMethod.dynamics(case, dt)` is the simulator of the case's collision scene as `wc.dynamics.Dynamics`
(`Replay`): built, its kernels compiled and warmed up with one frame on first use, outside the time the evaluate
stage takes for the rollout, which is the simulation (with the state maps) only.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from wc.dynamics import ObjectState, SteppedEpisode, as_command, stepped
from wc.eval.cases import Case
from wc.eval.config import MethodSpec
from wc.scene.config import SceneConfig
from wc.scene.resample import ResolutionMap
from wc.scene.scene import Scene, build_scene
from wc.sim.config import SimConfig
from wc.sim.newton_sim import NewtonSimulator

DT_TOLERANCE_S = 1e-9


def newton_sim_config(sim: SimConfig, spec: MethodSpec, device: str) -> SimConfig:
    """Params `sim` with a method's overrides, one world, on `device` (a warp device name); frame dt kept."""
    substeps = spec.substeps or sim.substeps
    return replace(sim, device=device, worlds=1, substeps=substeps, dt_s=sim.frame_dt_s / substeps,
                   iterations=spec.iterations or sim.iterations)


def coarse_scene_config(scene_cfg: SceneConfig, scene: Scene, scale: float) -> SceneConfig:
    """`scene_cfg` with each cloth object of `scene` at round(scale x target_vertices) vertices."""
    changes = {}
    for name, kind in scene.object_kinds.items():
        if kind == "cloth":
            obj = getattr(scene_cfg, name)
            changes[name] = replace(obj, target_vertices=max(1, round(obj.target_vertices * scale)))
    return replace(scene_cfg, **changes)


def warp_device(device: torch.device) -> str:
    """The warp device of a torch device: cpu or cuda:k."""
    return "cpu" if device.type == "cpu" else f"cuda:{device.index or 0}"


def scene_key(scene: Scene) -> tuple:
    """What makes two collision scenes the same simulator: predicted objects and held objects with their poses."""
    held = tuple((name, h.link, tuple(np.asarray(h.local_pose).tolist())) for name, h in scene.held.items())
    return tuple(scene.objects), held


@dataclass
class Replay:
    """Newton over one collision scene as `Dynamics` answering in the scene's (the store's) vertex order:
    `resolution` maps states to the simulator's coarser cloth and its frames back (frame 0 is the initial state)."""

    sim: NewtonSimulator
    resolution: ResolutionMap | None = None
    _episode: SteppedEpisode | None = field(default=None, init=False, repr=False)
    _coarse_last: ObjectState | None = field(default=None, init=False, repr=False)

    def _coarse(self, state: ObjectState) -> ObjectState:
        if self.resolution is None:
            return state
        return ObjectState(np.asarray(self.resolution.to_coarse(state.x), np.float32),
                           np.asarray(self.resolution.to_coarse(state.v), np.float32))

    def _fine(self, initial: ObjectState, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frames (T, N, 3) of the simulator in the scene's vertices (float64), frame 0 = `initial`."""
        if self.resolution is None:
            return x, v
        x, v = (self.resolution.to_fine(a[1:].astype(np.float64)) for a in (x, v))
        return np.concatenate([initial.x[None], x]), np.concatenate([initial.v[None], v])

    def rollout_batch(self, initial: list[ObjectState], actions: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(x, v) of (T, N, 3)] of episodes from their frame-0 states under actions (T, 14), not checked finite."""
        self._episode = None  # the simulator's state is the rollout's now
        out = self.sim.rollout_batch([self._coarse(s) for s in initial], actions)
        return [self._fine(s, x, v) for s, (x, v) in zip(initial, out)]

    def rollout(self, initial: ObjectState, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.rollout_batch([initial], [actions])[0]

    def start(self, initial: ObjectState, action: np.ndarray) -> None:
        self._coarse_last = self._coarse(initial)
        self.sim.start(self._coarse_last, action)
        self._episode = SteppedEpisode(initial, [as_command(action)])

    def step(self, state: ObjectState, action: np.ndarray) -> ObjectState:
        """NewtonSimulator.step in the scene's vertices: the simulator goes on from the state it last gave when
        `state` is the one the last start / step gave, else from `state` (its history forgotten)."""
        command = as_command(action)
        episode = stepped(self._episode, state)
        coarse = self._coarse_last if episode is self._episode else self._coarse(state)
        self._episode = None  # until the step is known finite: after a FloatingPointError, start again
        nxt = self.sim.step(coarse, command)
        x, v = self._fine(state, np.stack([coarse.x, nxt.x]), np.stack([coarse.v, nxt.v]))
        out = ObjectState(x[1], v[1])
        episode.actions.append(command)
        self._episode, self._coarse_last, episode.last = episode, nxt, out
        return out


class NewtonMethod:
    """Newton at one setting as an evaluated method; one simulator (`Replay`) per collision scene, built and warmed
    up on first use."""

    def __init__(self, spec: MethodSpec, scene_cfg: SceneConfig, sim_cfg: SimConfig, device: torch.device) -> None:
        if spec.kind != "newton":
            raise ValueError(f"NewtonMethod needs a method of kind 'newton', got {spec.kind!r}")
        self.cfg = newton_sim_config(sim_cfg, spec, warp_device(device))
        self.cfg.validate()
        self.scene_cfg = scene_cfg
        self.cloth_scale = spec.cloth_vertices_scale
        self._replays: dict[tuple, Replay] = {}

    def _build(self, scene: Scene) -> Replay:
        if self.cloth_scale is None or "cloth" not in scene.object_kinds.values():
            return Replay(NewtonSimulator(scene, self.cfg, worlds=1))
        held = {h.mesh.name: (h.link, h.local_pose) for h in scene.held.values()}
        coarse = build_scene(coarse_scene_config(self.scene_cfg, scene, self.cloth_scale), list(scene.objects),
                             held=held)
        return Replay(NewtonSimulator(coarse, self.cfg, worlds=1), ResolutionMap(scene, coarse))

    def dynamics(self, case: Case, dt: float) -> Replay:
        """The simulator of the case's collision scene (built and warmed up with one frame on first use: kernels
        compiled, buffers sized); ValueError when its frame dt is not the store's `dt` [s]."""
        if abs(self.cfg.frame_dt_s - dt) > DT_TOLERANCE_S:
            raise ValueError(f"Newton frame dt {self.cfg.frame_dt_s} s (sim.dt_s x sim.substeps) differs from the "
                             f"store's dt {dt} s")
        if case.scene.num_vertices != case.x.shape[1]:
            raise ValueError(f"episode {case.phase.episode}: {case.x.shape[1]} stored vertex rows, but its scene "
                             f"{list(case.scene.objects)} has {case.scene.num_vertices} vertices")
        key = scene_key(case.scene)
        if key not in self._replays:
            replay = self._build(case.scene)
            replay.rollout(ObjectState(case.x[0], case.v[0]), case.actions[:2])
            self._replays[key] = replay
        return self._replays[key]
