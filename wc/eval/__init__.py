"""Evaluation: held-out rollout errors, area-weighted penetration, long-rollout stability, and the `evaluate` stage.

    metrics      position / velocity MSE, pooled over vertices and frames, per task and per step
    penetration  exact signed distances of cloth to table, robot boxes and rigid meshes; area-weighted rates
    predictors   the Predictor interface; zero motion, constant velocity, WorldContact checkpoints, baselines
    methods      every evaluated method as wc.dynamics.Dynamics of a case (load_method, predict)
    newton_method  the Newton source simulator as a method, at its reference and cheaper settings
    stability    edge strain, divergence step, per-step curves of long rollouts
    cases        which stored phases are rolled out, with their actions, layout and collision scene
    stage        the stage itself (stages/evaluate.py is its command line)
    stress       the stress stage (stress_truth: its Newton ground truth; video: its side-by-side video)
"""

from wc.eval.config import EvaluateConfig, MethodSpec
from wc.eval.metrics import ErrorTally, squared_error
from wc.eval.penetration import PenetrationTally, cloth_signed_distance, mesh_signed_distance, penetrating_area_pct
from wc.eval.predictors import ConstantVelocity, Predictor, WorldContactPredictor, ZeroMotion, load_predictor
from wc.eval.stability import StabilityCurve, first_divergence, max_edge_strain

__all__ = [
    "ConstantVelocity", "ErrorTally", "EvaluateConfig", "MethodSpec", "PenetrationTally", "Predictor",
    "StabilityCurve", "WorldContactPredictor", "ZeroMotion", "cloth_signed_distance", "first_divergence",
    "load_predictor", "max_edge_strain", "mesh_signed_distance", "penetrating_area_pct", "squared_error",
]
