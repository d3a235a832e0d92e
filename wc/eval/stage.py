"""Stage `evaluate`: held-out rollouts of every method (reports/metrics.json, the Table 1 analogue) and long
stability rollouts (reports/stability.csv + reports/stability.png).

Held-out data: the store's test split; without one, the validation data training held out
(wc.train.loop.prepare_data: val split, else its held-out part of the train episodes); the report says which.
Every held-out span (a layout phase, wc.train.data.episode_phases, or a held-out block) is rolled out
autoregressively under the recorded prescribed inputs from its first frame to its end (capped at episode_frames
steps: the whole episode) and from up to phase_starts frames spread over its motion phases (approach, grasp, lift,
hold, release, drop; rollout_frames steps each): wc.eval.rollout_plan. The report has every method's MSE over all
of them (overall and per task), per motion phase and over the whole rollouts, and `whole_episode`: the subject's
(evaluate.subject) mean and worst per-task ratio of the best baseline's whole-episode position MSE to its own
(wc.eval.task_ratios), beside the pooled ratio, and its penetration there. A model of past frames (the particle
baselines) is given the recorded frames of the span before its start frame. Long rollouts take, per task,
the longest phases (test split, else every episode) for min(stability_frames, phase length - 1) steps.

Methods come from params `evaluate.methods` (wc.eval.methods: each one is rolled out as `wc.dynamics.Dynamics`
over a case's scene and recorded inputs); a checkpoint directory that does not exist is skipped and
listed under `skipped` in the report. "ground_truth" (the recorded frames) is scored beside them as the
penetration and strain floor of the data itself.

The speed-accuracy chart (speed_accuracy.{csv,png}, report key `speed_accuracy`) compares every method on the
same held-out rollouts of rollout_frames steps from a span's first frame: every span's, or `chart_max_cases` spans'
taking the tasks in turn. The Newton methods
(kind newton: the source simulator at its reference and cheaper settings) cost real simulation, so they run on
the chart's rollouts only and appear in the chart and its report block, not in `methods` (all held-out rollouts)
nor in the long rollouts. Speed is the frame dt over the wall time per predicted step, rollout only: Newton's
construction, compilation and warm-up are not timed, nor is every other method's first chart rollout, made once
untimed before the timed one (compilation, CUDA-graph capture).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
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
from wc.eval.map_back import MapBackTally
from wc.eval.metrics import squared_error
from wc.eval.penetration import cloth_signed_distance, penetrating_area_pct
from wc.eval.plots import SPEED_ACCURACY_HEADER, plot_speed_accuracy, plot_stability, speed_accuracy_rows
from wc.eval.methods import LearnedMethod, Method, load_method, predict
from wc.eval.newton_method import NewtonMethod
from wc.eval.rollout_plan import CHART, plan_rollouts
from wc.eval.scores import MethodScores
from wc.eval.task_ratios import task_ratios
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
REFERENCE_KINDS = ("baseline", "zero_motion", "constant_velocity")  # what the subject's whole-episode ratios compare


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
    """Held-out scores: `scores` over every scored rollout (not the Newton methods), `chart` over the chart's
    rollouts (every method), the rollouts made (`rolled`, `charted`), and the particle baselines' map-back floor
    over the scored rollouts' recorded frames (`map_back`, wc.eval.map_back)."""

    scores: dict[str, MethodScores]
    chart: dict[str, MethodScores]
    rolled: list[dict[str, Any]]
    charted: list[dict[str, Any]]
    map_back: MapBackTally


def held_out_scores(reader: CaseReader, phases: list[Phase], methods: dict[str, Method],
                    cfg: EvaluateConfig, dt: float) -> HeldOut:
    """Scores of the recorded data and every method over the held-out rollouts of `phases`
    (wc.eval.rollout_plan); the Newton methods roll out the chart's rollouts only. A phase start at a span's first
    frame is scored on the head of the span's whole rollout (the same frames), not rolled out (nor timed) again."""
    band = cfg.contact_band_m

    def tallies(names: list[str]) -> dict[str, MethodScores]:
        return {m: MethodScores(cfg.rollout_frames, cfg.episode_frames, cfg.penetration_depth_m, band) for m in names}

    chart = set(chart_phases(reader.store, phases, cfg.chart_max_cases))
    plan = plan_rollouts(reader.store, phases, cfg.rollout_frames, cfg.episode_frames, cfg.phase_starts, chart)
    newton = {n: isinstance(m, NewtonMethod) for n, m in methods.items()}
    out = HeldOut(tallies([GROUND_TRUTH, *(n for n in methods if not newton[n])]), tallies(list(methods)), [], [],
                  MapBackTally(max(cfg.rollout_frames, cfg.episode_frames)))
    warmed: set[str] = set()
    whole: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # the span's whole rollout: x, v, signed distance
    for planned in tqdm(plan, desc="evaluate held-out", unit="rollout"):
        case = reader.case(planned.span, planned.frames, planned.start)
        rollout = {"episode": case.phase.episode, "task": case.task, "start_frame": case.start, "steps": case.steps,
                   "label": planned.label}
        charted, scored = planned.charted(chart, cfg.rollout_frames), planned.label != CHART
        if scored:
            out.rolled.append(rollout)
        if charted:
            out.charted.append(rollout)
        if scored:
            truth_x, truth_v = case.x[1:].astype(np.float64), case.v[1:].astype(np.float64)
            out.scores[GROUND_TRUTH].add(case, truth_x, truth_v,
                                         cloth_signed_distance(case.scene, truth_x, case.link_poses[1:], band),
                                         planned.label)
            for name, method in methods.items():
                out.map_back.add(name, method, case)
        # a phase start at the span's first frame is the head of its whole rollout (autoregressive, deterministic)
        reuse = planned.whole or (planned.start == planned.span.start and not charted)
        if planned.whole:
            whole = {}
        for name, method in methods.items():
            if newton[name] and not charted:
                continue
            if reuse and name in whole and len(whole[name][0]) >= case.steps:
                x, v, signed_distance = (a[:case.steps] for a in whole[name])
                out.scores[name].add(case, x, v, signed_distance, planned.label)
                continue
            dynamics = method.dynamics(case, dt)  # Newton: built, compiled, warmed up on first use; not timed
            if charted and not newton[name] and name not in warmed:  # the first charted rollout once untimed:
                predict(dynamics, case)  # compilation, graph capture
                warmed.add(name)
            t0 = time.perf_counter()
            x, v = predict(dynamics, case)
            seconds = time.perf_counter() - t0
            signed_distance = cloth_signed_distance(case.scene, x, case.link_poses[1:], band)
            if planned.whole:
                whole[name] = (x, v, signed_distance)
            for table in ([out.chart] if charted else []) + ([out.scores] if scored and not newton[name] else []):
                table[name].seconds += seconds
                table[name].steps += case.steps
                table[name].add(case, x, v, signed_distance, planned.label)
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


def whole_episode(summaries: dict[str, dict[str, Any]], cfg: EvaluateConfig) -> dict[str, Any] | None:
    """The subject's whole-episode ratios against every evaluated baseline and reference (wc.eval.task_ratios),
    with its pooled MSE and penetration over those rollouts; None when the subject or every baseline is missing."""
    baselines = [m for m in summaries if cfg.methods[m].kind in REFERENCE_KINDS]
    if cfg.subject not in summaries or not baselines:
        return None
    whole = {m: summaries[m]["whole_episode"] for m in [cfg.subject, *baselines]}
    per_task = {m: {t: row["position_mse_m2"] for t, row in w["per_task"].items()} for m, w in whole.items()}
    pooled = {m: w["position_mse_m2"] for m, w in whole.items()}
    return {"subject": cfg.subject, "baselines": baselines, **task_ratios(per_task, pooled, cfg.subject, baselines),
            "penetration_pct": whole[cfg.subject]["penetration_rate_pct"],
            "subject_position_mse_m2": pooled[cfg.subject], "rollouts": whole[cfg.subject]["rollouts"]}


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
        "whole_episode": whole_episode(summaries, cfg),
        "map_back": held_out.map_back.summary(),
        "held_out": {"source": held_source, "rollouts": len(held_out.rolled), "rollout_frames": cfg.rollout_frames,
                     "episode_frames": cfg.episode_frames, "phase_starts": cfg.phase_starts,
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
    lines += [f"  {name:28s} map-back floor {fmt(m['position_mse_m2'], '.3e')} m² (perfect particles: "
              f"{', '.join(str(size['particles']) for size in m['layouts'])} of "
              f"{', '.join(str(size['vertices']) for size in m['layouts'])} vertices)"
              for name, m in r.get("map_back", {}).items()]
    lines += [f"  {name:28s} skipped: {why}" for name, why in r["skipped"].items()]
    w = r.get("whole_episode")
    if w:
        lines.append(f"  whole episodes: best baseline / {w['subject']} position MSE {fmt(w['mean_task_ratio'], '.2f')}x "
                     f"(mean over tasks; worst task {fmt(w['worst_task_ratio'], '.2f')}x, pooled "
                     f"{fmt(w['pooled_ratio'], '.2f')}x), penetration {fmt(w['penetration_pct'], '.2f')} %")
    return "\n".join(lines)
