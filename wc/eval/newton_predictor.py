"""The Newton source simulator as an evaluated method, at its reference setting or a cheaper one.

Each held-out case is re-simulated from its first stored frame (cloth vertices x, v as stored; rigid objects
posed from their stored vertices, as NewtonSimulator writes any state) under the case's recorded 14-D actions,
in the case's own collision scene (held objects included), and answered in the store's vertex order, so the
evaluate metrics apply unchanged. Settings (params `evaluate.methods`, kind `newton`):

    iterations            VBD iterations per solver step (params sim.iterations)
    substeps              solver steps per frame; the solver dt is frame dt / substeps, the frame dt stays
    cloth_vertices_scale  every cloth mesh rebuilt at this x its target_vertices; the stored frame-0 state is
                          mapped onto the coarse mesh and the result back (wc.scene.resample, rest space)

Simulator construction, kernel compilation and one warm-up rollout happen in `prepare`, outside the time the
evaluate stage takes for the rollout; `rollout_case` is the simulation (with the state maps) only.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from wc.dynamics import ObjectState
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
    """A simulator of one collision scene; `resolution` maps the stored state to its coarser cloth and back."""

    sim: NewtonSimulator
    resolution: ResolutionMap | None = None

    def simulate(self, x0: np.ndarray, v0: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """x, v (T-1, N, 3) float64 of frames 1..T-1 from x0, v0 (N, 3) in the stored layout, actions (T, 14)."""
        if self.resolution is not None:
            x0, v0 = self.resolution.to_coarse(x0), self.resolution.to_coarse(v0)
        x, v = self.sim.rollout(ObjectState(np.asarray(x0, np.float32), np.asarray(v0, np.float32)), actions)
        x, v = x[1:].astype(np.float64), v[1:].astype(np.float64)
        if self.resolution is not None:
            x, v = self.resolution.to_fine(x), self.resolution.to_fine(v)
        return x, v


class NewtonPredictor:
    """Newton at one setting; one simulator per collision scene, built and warmed up on first use."""

    def __init__(self, spec: MethodSpec, scene_cfg: SceneConfig, sim_cfg: SimConfig, device: torch.device) -> None:
        if spec.kind != "newton":
            raise ValueError(f"NewtonPredictor needs a method of kind 'newton', got {spec.kind!r}")
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

    def _check(self, case: Case, actions: np.ndarray) -> None:
        if case.scene.num_vertices != case.x.shape[1]:
            raise ValueError(f"episode {case.phase.episode}: {case.x.shape[1]} stored vertex rows, but its scene "
                             f"{list(case.scene.objects)} has {case.scene.num_vertices} vertices")
        if actions.shape != (len(case.x), 14):
            raise ValueError(f"episode {case.phase.episode}: actions must be ({len(case.x)}, 14), got {actions.shape}")

    def prepare(self, case: Case, actions: np.ndarray) -> None:
        """Build the case's simulator on first use and warm it up with one frame (kernels compiled, buffers sized)."""
        self._check(case, actions)
        key = scene_key(case.scene)
        if key not in self._replays:
            replay = self._build(case.scene)
            replay.simulate(case.x[0], case.v[0], actions[:2])
            self._replays[key] = replay

    def rollout_case(self, case: Case, actions: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """x, v (S, N, 3) float64 of the case's frames 1..S, re-simulated from its frame 0 under actions (S+1, 14)."""
        if abs(self.cfg.frame_dt_s - dt) > DT_TOLERANCE_S:
            raise ValueError(f"Newton frame dt {self.cfg.frame_dt_s} s (sim.dt_s x sim.substeps) differs from the "
                             f"store's dt {dt} s")
        self.prepare(case, actions)
        return self._replays[scene_key(case.scene)].simulate(case.x[0], case.v[0], actions)
