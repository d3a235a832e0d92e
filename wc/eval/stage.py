"""Stage `evaluate`: held-out rollouts of every method (reports/metrics.json, the Table 1 analogue) and long
stability rollouts (reports/stability.csv + reports/stability.png).

Held-out data: the store's test split; without one, the validation data training held out
(wc.train.loop.prepare_data: val split, else its held-out part of the train episodes); the report says which.
Every phase (wc.train.data.episode_phases) is rolled out autoregressively from its first frame under the
recorded prescribed inputs for min(rollout_frames, phase length - 1) steps. Long rollouts take, per task,
the longest phases (test split, else every episode) for min(stability_frames, phase length - 1) steps.

Methods come from params `evaluate.methods`; a checkpoint directory that does not exist is skipped and
listed under `skipped` in the report. "ground_truth" (the recorded frames) is scored beside them as the
penetration and strain floor of the data itself.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from wc.config import ParamsError, load_section, params_hash
from wc.data.store import TrajectoryStore
from wc.devices import resolve_device
from wc.eval.cases import Case, CaseReader, held_out_phases, long_phases
from wc.eval.config import EvaluateConfig
from wc.eval.metrics import ErrorTally, finite_or_none, squared_error
from wc.eval.penetration import PenetrationTally, cloth_signed_distance, penetrating_area_pct
from wc.eval.plots import SPEED_ACCURACY_HEADER, plot_speed_accuracy, plot_stability, speed_accuracy_rows
from wc.eval.predictors import Predictor, WorldContactPredictor, load_predictor
from wc.eval.stability import (CSV_HEADER, StabilityCurve, csv_rows, divergence_summary, first_divergence,
                              max_edge_strain)
from wc.model.config import ModelConfig
from wc.reports import environment_info, write_csv_atomic, write_json_atomic
from wc.scene.config import SceneConfig
from wc.train.config import TrainConfig
from wc.train.data import Phase

SECTIONS = ["evaluate", "scene", "model", "train"]
GROUND_TRUTH = "ground_truth"


def load_methods(cfg: EvaluateConfig, train_cfg: TrainConfig, tag_scale: float, device: torch.device
                 ) -> tuple[dict[str, Predictor], dict[str, str]]:
    """(predictors by name, skipped methods with the reason): absent checkpoint directories are skipped."""
    predictors, skipped = {}, {}
    for name, spec in cfg.methods.items():
        if name == GROUND_TRUTH:
            raise ParamsError(f"evaluate.methods.{name}: the name {GROUND_TRUTH!r} is reserved for the recorded data")
        try:
            predictor = load_predictor(spec, train_cfg, device)
        except FileNotFoundError as err:
            skipped[name] = str(err)
            continue
        except ImportError as err:
            skipped[name] = f"baseline code not importable: {err}"
            continue
        if isinstance(predictor, WorldContactPredictor) and predictor.tag_scale != tag_scale:
            raise ValueError(f"evaluate.methods.{name}: checkpoint tag_scale {predictor.tag_scale} differs from "
                             f"params model.tag_scale {tag_scale}; layouts are built with the params value")
        predictors[name] = predictor
    return predictors, skipped


def predict(predictor: Predictor, case: Case, dt: float, device: torch.device) -> tuple[np.ndarray, np.ndarray]:
    """Predicted x, v (S, N, 3) for frames 1..S of a case (float64 numpy; NaN after a raised FloatingPointError)."""
    x0, v0, poses = case.inputs(device)
    shape = (1, case.steps, *case.x.shape[1:])
    try:
        x, v = predictor.rollout(case.layout, x0, v0, poses, dt)
    except FloatingPointError:
        return np.full(shape[1:], np.nan), np.full(shape[1:], np.nan)
    x, v = torch.as_tensor(x), torch.as_tensor(v)  # a baseline may answer in numpy
    if tuple(x.shape) != shape or tuple(v.shape) != shape:
        raise ValueError(f"{type(predictor).__name__}.rollout returned x {tuple(x.shape)}, v {tuple(v.shape)}; "
                         f"expected {shape}")
    return x[0].detach().double().cpu().numpy(), v[0].detach().double().cpu().numpy()


@dataclass
class MethodScores:
    """A method's held-out errors and penetration (overall and per task) and its rollout time."""

    errors: ErrorTally
    depth_m: float
    band_m: float
    penetration: PenetrationTally = field(init=False)
    task_penetration: dict[str, PenetrationTally] = field(default_factory=dict)
    seconds: float = 0.0
    steps: int = 0

    def __post_init__(self) -> None:
        self.penetration = PenetrationTally(self.depth_m, self.band_m)

    def add(self, case: Case, x: np.ndarray, v: np.ndarray, signed_distance: np.ndarray) -> None:
        """One rollout's predicted x, v (S, N, 3) and its cloth signed distances (S, N_cloth)."""
        self.errors.add(case.task, x, v, case.x[1:], case.v[1:])
        self.penetration.add(signed_distance, case.cloth_area)
        task = self.task_penetration.setdefault(case.task, PenetrationTally(self.depth_m, self.band_m))
        task.add(signed_distance, case.cloth_area)

    @staticmethod
    def _rates(tally: PenetrationTally) -> dict[str, float | None]:
        return {"penetration_rate_pct": finite_or_none(tally.rate_pct),
                "contact_penetration_rate_pct": finite_or_none(tally.contact_rate_pct)}

    def summary(self) -> dict[str, Any]:
        out = {**self.errors.summary(), **self._rates(self.penetration)}
        for task, tally in self.task_penetration.items():
            out["per_task"][task].update(self._rates(tally))
        out["s_per_step"] = finite_or_none(self.seconds / self.steps) if self.steps else None
        return out


def stability_curve(method: str, case: Case, x: np.ndarray, signed_distance: np.ndarray,
                    cfg: EvaluateConfig) -> StabilityCurve:
    """Per-step curves of one long rollout x (S, N, 3) and its divergence step."""
    error = squared_error(x, case.x[1:])
    strain = max_edge_strain(x, case.layout.edges.cpu().numpy(), case.layout.rest_lengths.cpu().numpy())
    penetration = penetrating_area_pct(signed_distance, case.cloth_area, cfg.penetration_depth_m)
    finite = np.isfinite(x).all(axis=(1, 2))
    step = first_divergence(finite, strain, penetration, cfg.divergence_strain, cfg.divergence_penetration_pct)
    return StabilityCurve(method, case.task, case.phase.episode, case.phase.start, error,
                          penetration, strain, step)


def held_out_scores(reader: CaseReader, phases: list[Phase], predictors: dict[str, Predictor], cfg: EvaluateConfig,
                    dt: float) -> tuple[dict[str, MethodScores], list[dict[str, Any]]]:
    """Scores of the recorded data and every method over rollouts of up to rollout_frames steps from each
    phase's first frame, and the list of rollouts made."""
    band = cfg.contact_band_m
    scores = {m: MethodScores(ErrorTally(cfg.rollout_frames), cfg.penetration_depth_m, band)
              for m in [GROUND_TRUTH, *predictors]}
    rolled = []
    for phase in tqdm(phases, desc="evaluate held-out", unit="rollout"):
        if phase.stop - phase.start < 2:
            continue
        case = reader.case(phase, cfg.rollout_frames + 1)
        rolled.append({"episode": phase.episode, "task": case.task, "start_frame": phase.start, "steps": case.steps})
        truth_x, truth_v = case.x[1:].astype(np.float64), case.v[1:].astype(np.float64)
        scores[GROUND_TRUTH].add(case, truth_x, truth_v,
                                 cloth_signed_distance(case.scene, truth_x, case.link_poses[1:], band))
        for name, predictor in predictors.items():
            t0 = time.perf_counter()
            x, v = predict(predictor, case, dt, reader.device)
            scores[name].seconds += time.perf_counter() - t0
            scores[name].steps += case.steps
            scores[name].add(case, x, v, cloth_signed_distance(case.scene, x, case.link_poses[1:], band))
    return scores, rolled


def stability_curves(reader: CaseReader, phases: list[Phase], predictors: dict[str, Predictor],
                     cfg: EvaluateConfig, dt: float) -> list[StabilityCurve]:
    """Curves of the recorded data and every method over rollouts of up to stability_frames steps."""
    curves = []
    for phase in tqdm(phases, desc="evaluate stability", unit="rollout"):
        if phase.stop - phase.start < 2:
            continue
        case = reader.case(phase, cfg.stability_frames + 1)
        for name, predictor in [(GROUND_TRUTH, None), *predictors.items()]:
            x = case.x[1:].astype(np.float64) if predictor is None else predict(predictor, case, dt, reader.device)[0]
            sd = cloth_signed_distance(case.scene, x, case.link_poses[1:], cfg.contact_band_m)
            curves.append(stability_curve(name, case, x, sd, cfg))
    return curves


def evaluate(params: dict[str, Any], store_path: str | Path = "data/source/trajectories.zarr",
             metrics: str | Path = "reports/metrics.json", stability_csv: str | Path = "reports/stability.csv",
             stability_png: str | Path = "reports/stability.png") -> dict[str, Any]:
    """Run the held-out and long rollouts of every method; write the metrics, the stability curves and the
    speed-accuracy chart (speed_accuracy.{csv,png} beside `metrics`); return the metrics dict."""
    cfg = load_section(params, "evaluate", EvaluateConfig)
    scene_cfg = load_section(params, "scene", SceneConfig)
    model_cfg = load_section(params, "model", ModelConfig)
    train_cfg = load_section(params, "train", TrainConfig)
    if not Path(store_path).exists():
        raise FileNotFoundError(f"evaluate: trajectory store not found: {store_path} (run the validate stage first)")
    started = time.perf_counter()
    torch.manual_seed(cfg.seed)
    device = resolve_device(cfg.device, "evaluate.device")
    store = TrajectoryStore(store_path)
    dt = float(store.dt)
    predictors, skipped = load_methods(cfg, train_cfg, model_cfg.tag_scale, device)
    reader = CaseReader(store, scene_cfg, model_cfg.tag_scale, device)

    held, held_source = held_out_phases(store, train_cfg)
    if not held:
        raise ValueError(f"evaluate: {store_path} has no held-out phase to roll out ({held_source})")
    scores, rolled = held_out_scores(reader, held, predictors, cfg, dt)
    long, long_source = long_phases(store, cfg.stability_per_task)
    curves = stability_curves(reader, long, predictors, cfg, dt)

    write_csv_atomic(stability_csv, CSV_HEADER, csv_rows(curves, dt))
    plot_stability(curves, stability_png, dt, cfg.divergence_strain, cfg.divergence_penetration_pct)
    summaries = {m: s.summary() for m, s in scores.items()}
    ground_truth = summaries.pop(GROUND_TRUTH)
    speed_rows = speed_accuracy_rows(summaries, dt)  # beside the metrics: speed_accuracy.{csv,png}
    write_csv_atomic(Path(metrics).with_name("speed_accuracy.csv"), SPEED_ACCURACY_HEADER, speed_rows)
    plot_speed_accuracy(speed_rows, Path(metrics).with_name("speed_accuracy.png"))
    stability = divergence_summary(curves)
    result = {
        "methods": summaries,
        "ground_truth": {k: ground_truth[k] for k in ("penetration_rate_pct", "contact_penetration_rate_pct")},
        "skipped": skipped,
        "held_out": {"source": held_source, "rollouts": len(rolled), "rollout_frames": cfg.rollout_frames,
                     "phases": rolled},
        "stability": {"source": long_source, "stability_frames": cfg.stability_frames,
                      "divergence": {"strain": cfg.divergence_strain,
                                     "penetration_pct": cfg.divergence_penetration_pct},
                      "methods": stability},
        "penetration": {"depth_m": cfg.penetration_depth_m, "contact_band_m": cfg.contact_band_m},
        "store": str(store_path),
        "params_hash": params_hash(params, SECTIONS),
        "wall_s": time.perf_counter() - started,
        "environment": environment_info(str(device)),
    }
    write_json_atomic(metrics, result)
    return result
