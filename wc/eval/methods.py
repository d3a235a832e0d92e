"""Every method evaluate and stress compare, as `wc.dynamics.Dynamics` of one case.

A method is loaded once from its params entry (`load_method`); `method.dynamics(case, dt)` is the method over the
case's scene with whatever the method needs of the case folded in (not timed), and `predict` rolls it out from the
case's frame 0 under the case's commanded actions (what the speed-accuracy chart times):

    LearnedMethod  a learned predictor (WorldContact, a baseline, zero motion, constant velocity) as LearnedDynamics,
                   stepping the case's recorded link, held-object and environment poses (RecordedInputs); a
                   model of past frames is given the case's recorded frames before its start
    NewtonMethod   the source simulator at one setting (wc.eval.newton_method): the simulator of the case's
                   collision scene, built and warmed up on first use
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from wc.dynamics import Dynamics, ObjectState
from wc.eval.cases import Case
from wc.eval.config import MethodSpec
from wc.eval.newton_method import NewtonMethod
from wc.eval.predictors import Predictor, load_predictor
from wc.model.learned_dynamics import LearnedDynamics
from wc.model.prescribed_inputs import RecordedInputs
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.train.config import TrainConfig


class Method(Protocol):
    def dynamics(self, case: Case, dt: float) -> Dynamics:
        """The method over the case's scene and recorded prescribed inputs, frame dt `dt` [s]."""
        ...


@dataclass(frozen=True)
class LearnedMethod:
    """A learned predictor or reference, rolled out on `device` under each case's recorded body poses."""

    predictor: Predictor
    device: torch.device

    def dynamics(self, case: Case, dt: float) -> LearnedDynamics:
        inputs = RecordedInputs(case.actions, case.poses, case.layout.bodies)
        return LearnedDynamics(self.predictor, case.layout, inputs, dt, self.device, case.recorded_past())


def load_method(spec: MethodSpec, train_cfg: TrainConfig, device: torch.device,
                scene_cfg: SceneConfig | None = None, sim_cfg: SimConfig | None = None) -> LearnedMethod | NewtonMethod:
    """The method a params entry names (kind newton needs the params `scene` and `sim` configs); errors as
    wc.eval.predictors.load_predictor (FileNotFoundError for an absent checkpoint directory)."""
    if spec.kind != "newton":
        return LearnedMethod(load_predictor(spec, train_cfg, device), device)
    if scene_cfg is None or sim_cfg is None:
        raise ValueError("a method of kind 'newton' needs the params `scene` and `sim` sections")
    return NewtonMethod(spec, scene_cfg, sim_cfg, device)


def predict(dynamics: Dynamics, case: Case) -> tuple[np.ndarray, np.ndarray]:
    """Predicted x, v (S, N, 3) float64 of the case's frames 1..S, rolled out from its frame 0 under its actions (NaN
    from where it diverged, and throughout after a raised FloatingPointError)."""
    shape = (case.steps + 1, *case.x.shape[1:])
    try:
        x, v = dynamics.rollout(ObjectState(case.x[0], case.v[0]), case.actions)
    except FloatingPointError:
        return np.full(shape, np.nan)[1:], np.full(shape, np.nan)[1:]
    if x.shape != shape or v.shape != shape:
        raise ValueError(f"{type(dynamics).__name__}.rollout returned x {x.shape}, v {v.shape}; expected {shape}")
    return x[1:].astype(np.float64), v[1:].astype(np.float64)
