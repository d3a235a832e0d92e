"""Stage `evaluate`: held-out rollouts of every method (reports/metrics.json, the Table 1 analogue) and long
stability rollouts (reports/stability.csv + reports/stability.png).

Held-out data: the store's test split; without one, the validation data training held out
(wc.train.loop.prepare_data: val split, else its held-out part of the train episodes); the report says which.
Every phase (wc.train.data.episode_phases) is rolled out autoregressively from its first frame under the
recorded prescribed inputs for min(rollout_frames, phase length - 1) steps. Long rollouts take, per task,
the longest phases (test split, else every episode) for min(stability_frames, phase length - 1) steps.

Methods come from params `evaluate.methods` (wc.eval.methods: each one is rolled out as `wc.dynamics.Dynamics`
over a case's scene and recorded inputs); a checkpoint directory that does not exist is skipped and
listed under `skipped` in the report. "ground_truth" (the recorded frames) is scored beside them as the
penetration and strain floor of the data itself.

The speed-accuracy chart (speed_accuracy.{csv,png}, report key `speed_accuracy`) compares every method on the
same held-out rollouts: all of them, or `chart_max_cases` of them taking the tasks in turn. The Newton methods
(kind newton: the source simulator at its reference and cheaper settings) cost real simulation, so they run on
the chart's rollouts only and appear in the chart and its report block, not in `methods` (all held-out rollouts)
nor in the long rollouts. Speed is the frame dt over the wall time per predicted step, rollout only: Newton's
construction, compilation and warm-up are not timed, nor is every other method's first chart rollout, made once
untimed before the timed one (compilation, CUDA-graph capture).
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
from wc.eval.config import EvaluateConfig, MethodSpec
from wc.eval.metrics import ErrorTally, finite_or_none, squared_error
from wc.eval.penetration import PenetrationTally, cloth_signed_distance, penetrating_area_pct
from wc.eval.plots import SPEED_ACCURACY_HEADER, plot_speed_accuracy, plot_stability, speed_accuracy_rows
from wc.eval.methods import LearnedMethod, Method, load_method, predict
from wc.eval.newton_method import NewtonMethod
from wc.model.predictor import WorldContactPredictor
from wc.eval.stability import (CSV_HEADER, StabilityCurve, csv_rows, divergence_summary, first_divergence,
                              max_edge_strain)
from wc.model.config import ModelConfig
from wc.model_ref import model_record
from wc.paths import EVALUATE
from wc.reports import environment_info, write_csv_atomic, write_json_atomic
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.train.config import TrainConfig
from wc.train.data import Phase

SECTIONS = ["evaluate", "scene", "model", "train", "sim"]
GROUND_TRUTH = "ground_truth"


def model_records(cfg: EvaluateConfig, methods: dict[str, Method]) -> dict[str, dict[str, Any]]:
    """Path and weights SHA-256 (wc/model_ref.py) of every loaded method that has a checkpoint."""
    return {m: model_record(spec.path) for m, spec in cfg.methods.items() if m in methods and spec.path}


def load_methods(cfg: EvaluateConfig, train_cfg: TrainConfig, tag_scale: float, device: torch.device,
                 scene_cfg: SceneConfig | None = None, sim_cfg: SimConfig | None = None
                 ) -> tuple[dict[str, Method], dict[str, str]]:
    """(methods by name, skipped methods with the reason): absent checkpoint directories are skipped."""
    methods, skipped = {}, {}
    for name, spec in cfg.methods.items():
        if name == GROUND_TRUTH:
            raise ParamsError(f"evaluate.methods.{name}: the name {GROUND_TRUTH!r} is reserved for the recorded data")
        try:
            method = load_method(spec, train_cfg, device, scene_cfg, sim_cfg)
        except FileNotFoundError as err:
            skipped[name] = str(err)
            continue
        except ImportError as err:
            skipped[name] = f"baseline code not importable: {err}"
            continue
        predictor = method.predictor if isinstance(method, LearnedMethod) else None
        if isinstance(predictor, WorldContactPredictor) and predictor.tag_scale != tag_scale:
            raise ValueError(f"evaluate.methods.{name}: checkpoint tag_scale {predictor.tag_scale} differs from "
                             f"params model.tag_scale {tag_scale}; layouts are built with the params value")
        methods[name] = method
    return methods, skipped


def past_frames(methods: dict[str, Method]) -> int:
    """Recorded frames before a rollout's start that some method reads (a particle baseline's history - 1)."""
    return max([getattr(m.predictor, "history", 1) - 1 for m in methods.values() if isinstance(m, LearnedMethod)],
               default=0)


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
    return StabilityCurve(method, case.task, case.phase.episode, case.start, error,
                          penetration, strain, step)


def chart_phases(store: TrajectoryStore, phases: list[Phase], max_cases: int | None) -> list[Phase]:
    """The held-out phases on the speed-accuracy chart: every one that can be rolled out, or the first
    `max_cases` taking the tasks in turn (each task's first phase in held-out order, then each one's second...)."""
    rollable = [p for p in phases if p.stop - p.start >= 2]
    if max_cases is None or len(rollable) <= max_cases:
        return rollable
    by_task: dict[str, list[Phase]] = {}
    for p in rollable:
        by_task.setdefault(str(store.episode_attrs(p.episode)["task"]), []).append(p)
    rounds = max(len(t) for t in by_task.values())
    return [t[k] for k in range(rounds) for t in by_task.values() if k < len(t)][:max_cases]


@dataclass
class HeldOut:
    """Held-out scores: `scores` over every rollout (not the Newton methods), `chart` over the chart's
    rollouts (every method), and the rollouts made (`rolled`, `charted`)."""

    scores: dict[str, MethodScores]
    chart: dict[str, MethodScores]
    rolled: list[dict[str, Any]]
    charted: list[dict[str, Any]]


def held_out_scores(reader: CaseReader, phases: list[Phase], methods: dict[str, Method],
                    cfg: EvaluateConfig, dt: float) -> HeldOut:
    """Scores of the recorded data and every method over rollouts of up to rollout_frames steps from each
    phase's first frame; the Newton methods roll out the chart's phases only."""
    band = cfg.contact_band_m

    def tallies(names: list[str]) -> dict[str, MethodScores]:
        return {m: MethodScores(ErrorTally(cfg.rollout_frames), cfg.penetration_depth_m, band) for m in names}

    on_chart = set(chart_phases(reader.store, phases, cfg.chart_max_cases))
    newton = {n: isinstance(m, NewtonMethod) for n, m in methods.items()}
    out = HeldOut(tallies([GROUND_TRUTH, *(n for n in methods if not newton[n])]), tallies(list(methods)), [], [])
    warmed: set[str] = set()
    for phase in tqdm(phases, desc="evaluate held-out", unit="rollout"):
        if phase.stop - phase.start < 2:
            continue
        case = reader.case(phase, cfg.rollout_frames + 1)
        rollout = {"episode": phase.episode, "task": case.task, "start_frame": phase.start, "steps": case.steps}
        out.rolled.append(rollout)
        charted = phase in on_chart
        if charted:
            out.charted.append(rollout)
        truth_x, truth_v = case.x[1:].astype(np.float64), case.v[1:].astype(np.float64)
        out.scores[GROUND_TRUTH].add(case, truth_x, truth_v,
                                     cloth_signed_distance(case.scene, truth_x, case.link_poses[1:], band))
        for name, method in methods.items():
            if newton[name] and not charted:
                continue
            dynamics = method.dynamics(case, dt)  # Newton: built, compiled, warmed up on first use; not timed
            if charted and not newton[name] and name not in warmed:  # the first charted rollout once untimed:
                predict(dynamics, case)  # compilation, graph capture
                warmed.add(name)
            t0 = time.perf_counter()
            x, v = predict(dynamics, case)
            seconds = time.perf_counter() - t0
            signed_distance = cloth_signed_distance(case.scene, x, case.link_poses[1:], band)
            for table in ([out.chart] if charted else []) + ([] if newton[name] else [out.scores]):
                table[name].seconds += seconds
                table[name].steps += case.steps
                table[name].add(case, x, v, signed_distance)
    return out


def stability_curves(reader: CaseReader, phases: list[Phase], methods: dict[str, Method],
                     cfg: EvaluateConfig, dt: float) -> list[StabilityCurve]:
    """Curves of the recorded data and every method (not the Newton methods: Newton is the data's own
    simulator) over rollouts of up to stability_frames steps."""
    methods = {n: m for n, m in methods.items() if not isinstance(m, NewtonMethod)}
    curves = []
    for phase in tqdm(phases, desc="evaluate stability", unit="rollout"):
        if phase.stop - phase.start < 2:
            continue
        case = reader.case(phase, cfg.stability_frames + 1)
        for name, method in [(GROUND_TRUTH, None), *methods.items()]:
            x = case.x[1:].astype(np.float64) if method is None else predict(method.dynamics(case, dt), case)[0]
            sd = cloth_signed_distance(case.scene, x, case.link_poses[1:], cfg.contact_band_m)
            curves.append(stability_curve(name, case, x, sd, cfg))
    return curves


def newton_setting(spec: MethodSpec, sim_cfg: SimConfig) -> dict[str, Any]:
    """The simulator setting of a Newton method, for the report."""
    substeps = spec.substeps or sim_cfg.substeps
    return {"iterations": spec.iterations or sim_cfg.iterations, "substeps": substeps,
            "dt_s": sim_cfg.frame_dt_s / substeps, "cloth_vertices_scale": spec.cloth_vertices_scale or 1.0}


def evaluate(params: dict[str, Any], store_path: str | Path = EVALUATE["store"],
             metrics: str | Path = EVALUATE["metrics"], stability_csv: str | Path = EVALUATE["stability_csv"],
             stability_png: str | Path = EVALUATE["stability_png"]) -> dict[str, Any]:
    """Run the held-out and long rollouts of every method; write the metrics, the stability curves and the
    speed-accuracy chart (speed_accuracy.{csv,png} beside `metrics`); return the metrics dict."""
    cfg = load_section(params, "evaluate", EvaluateConfig)
    scene_cfg = load_section(params, "scene", SceneConfig)
    model_cfg = load_section(params, "model", ModelConfig)
    train_cfg = load_section(params, "train", TrainConfig)
    newton = any(spec.kind == "newton" for spec in cfg.methods.values())
    sim_cfg = load_section(params, "sim", SimConfig) if newton else None
    if not Path(store_path).exists():
        raise FileNotFoundError(f"evaluate: trajectory store not found: {store_path} (run the validate stage first)")
    started = time.perf_counter()
    torch.manual_seed(cfg.seed)
    device = resolve_device(cfg.device, "evaluate.device")
    store = TrajectoryStore(store_path)
    dt = float(store.dt)
    methods, skipped = load_methods(cfg, train_cfg, model_cfg.tag_scale, device, scene_cfg, sim_cfg)
    reader = CaseReader(store, scene_cfg, model_cfg.tag_scale, device, past_frames(methods))

    held, held_source = held_out_phases(store, train_cfg)
    if not held:
        raise ValueError(f"evaluate: {store_path} has no held-out phase to roll out ({held_source})")
    held_out = held_out_scores(reader, held, methods, cfg, dt)
    long, long_source = long_phases(store, cfg.stability_per_task)
    curves = stability_curves(reader, long, methods, cfg, dt)

    write_csv_atomic(stability_csv, CSV_HEADER, csv_rows(curves, dt))
    plot_stability(curves, stability_png, dt, cfg.divergence_strain, cfg.divergence_penetration_pct)
    summaries = {m: s.summary() for m, s in held_out.scores.items()}
    ground_truth = summaries.pop(GROUND_TRUTH)
    chart = {m: s.summary() for m, s in held_out.chart.items()}
    kinds = {m: cfg.methods[m].kind for m in chart}
    speed_rows = speed_accuracy_rows(chart, dt, kinds)  # beside the metrics: speed_accuracy.{csv,png}
    write_csv_atomic(Path(metrics).with_name("speed_accuracy.csv"), SPEED_ACCURACY_HEADER, speed_rows)
    plot_speed_accuracy(speed_rows, Path(metrics).with_name("speed_accuracy.png"), len(held_out.charted))
    stability = divergence_summary(curves)
    result = {
        "methods": summaries,
        "ground_truth": {k: ground_truth[k] for k in ("penetration_rate_pct", "contact_penetration_rate_pct")},
        "skipped": skipped,
        "held_out": {"source": held_source, "rollouts": len(held_out.rolled), "rollout_frames": cfg.rollout_frames,
                     "phases": held_out.rolled},
        "speed_accuracy": {"rollouts": len(held_out.charted), "chart_max_cases": cfg.chart_max_cases,
                           "phases": held_out.charted, "methods": chart,
                           "newton": {m: newton_setting(cfg.methods[m], sim_cfg) for m in chart
                                      if cfg.methods[m].kind == "newton"}},
        "stability": {"source": long_source, "stability_frames": cfg.stability_frames,
                      "divergence": {"strain": cfg.divergence_strain,
                                     "penetration_pct": cfg.divergence_penetration_pct},
                      "methods": stability},
        "penetration": {"depth_m": cfg.penetration_depth_m, "contact_band_m": cfg.contact_band_m},
        "kinds": {m: spec.kind for m, spec in cfg.methods.items() if m in methods},
        "models": model_records(cfg, methods),
        "dt": dt,
        "store": str(store_path),
        "params_hash": params_hash(params, SECTIONS),
        "wall_s": time.perf_counter() - started,
        "environment": environment_info(str(device)),
    }
    write_json_atomic(metrics, result)
    return result


def evaluate_summary(r: dict[str, Any]) -> str:
    """The lines `python -m stages.evaluate` prints: one per method, one per skipped method."""
    def fmt(value: float | None, spec: str) -> str:
        return "diverged" if value is None else format(value, spec)

    lines = [f"evaluate: {r['held_out']['rollouts']} held-out rollouts ({r['held_out']['source']}), "
             f"{r['wall_s']:.0f} s"]
    for name, m in r["methods"].items():
        div = r["stability"]["methods"].get(name, {})
        lines.append(f"  {name:28s} x MSE {fmt(m['position_mse_m2'], '.3e')} m²  "
                     f"v MSE {fmt(m['velocity_mse_m2_s2'], '.3e')} m²/s²  "
                     f"penetration {fmt(m.get('penetration_rate_pct'), '.2f')} % "
                     f"(contact {fmt(m.get('contact_penetration_rate_pct'), '.2f')} %)  "
                     f"diverged {div.get('diverged', 0)}/{div.get('rollouts', 0)} long rollouts")
    lines += [f"  {name:28s} skipped: {why}" for name, why in r["skipped"].items()]
    return "\n".join(lines)
