"""Stage `stress`: stress cases a user would hit (faster motion, a heavier / lighter bag, an unseen grasp, two
objects, a held object released mid-rollout), every evaluate method rolled out from frame 0 against Newton
ground truth -> reports/stress.csv, reports/stress.png, reports/stress_curves.csv, reports/stress.json, and a
side-by-side video of one case (wc.eval.video).

Ground truth: wc.eval.stress_truth (data/stress/trajectories.zarr, reused while its params hash matches).
Rollouts: each episode from frame 0 for min(stress.rollout_frames, frames - 1) steps, every method as
`wc.dynamics.Dynamics` of each phase's case (wc.eval.methods) under the recorded actions and prescribed inputs. A hand-off episode is one rollout across its release: the first phase is rolled out to
the release frame, and the second starts from the predicted state of the objects that stay predicted plus
the recorded state of the released object (which until then followed its gripper, a prescribed pose).
Scores per case and method, pooled over the case's episodes: position and velocity MSE (wc.eval.metrics),
penetration rate (wc.eval.penetration), the largest edge strain and the first divergence step with the
evaluate section's bounds (wc.eval.stability); "ground_truth" is scored beside the methods as the floor.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from wc.config import load_section, params_hash
from wc.data.store import TrajectoryStore
from wc.devices import resolve_device
from wc.eval.cases import Case, CaseReader
from wc.eval.config import EvaluateConfig
from wc.eval.metrics import ErrorTally, finite_or_none
from wc.eval.penetration import PenetrationTally, cloth_signed_distance
from wc.eval.methods import Method, predict
from wc.eval.newton_method import NewtonMethod
from wc.eval.stability import CSV_HEADER, StabilityCurve, csv_rows
from wc.eval.stage import GROUND_TRUTH, load_methods, model_records, stability_curve
from wc.eval.stress_config import StressConfig
from wc.eval.stress_truth import ground_truth
from wc.eval.video import side_by_side_video
from wc.model.config import ModelConfig
from wc.paths import STRESS
from wc.reports import environment_info, pyplot, save_figure_atomic, write_csv_atomic, write_json_atomic
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.smoke import smoke_label
from wc.train.config import TrainConfig
from wc.train.data import episode_phases

SECTIONS = ["stress", "evaluate", "scene", "sim", "tasks", "validate", "model", "train"]
REFERENCE = "constant_velocity"  # errors are also given relative to this method's, per case
STRESS_HEADER = ["case", "task", "method", "episodes", "steps", "position_mse_m2", "velocity_mse_m2_s2",
                 f"position_mse_vs_{REFERENCE}", "penetration_rate_pct", "max_edge_strain", "divergence_step",
                 "diverged_episodes"]


@dataclass
class Rollout:
    """One method's rollout of one episode from frame 0: per phase the case and predicted x, v (S_k, N_k, 3)."""

    episode: str
    phases: list[tuple[Case, np.ndarray, np.ndarray]]

    def full_x(self, store: TrajectoryStore) -> np.ndarray:
        """(S, N_e, 3) predicted x of frames 1..S in the episode's row layout; rows a phase does not predict (a
        held object before its release) are the recorded ones."""
        layout = store.episode_layout(self.episode)
        steps = sum(len(x) for _, x, _ in self.phases)
        out = store.read_window(self.episode, 1, steps)["x"].astype(np.float64)
        k = 0
        for case, x, _ in self.phases:
            rows = np.concatenate([np.arange(layout[o].start, layout[o].stop) for o in case.phase.layout[0]])
            out[k:k + len(x), rows] = x
            k += len(x)
        return out


def _carried_start(store: TrajectoryStore, case: Case, previous: Rollout) -> Case:
    """`case` with frame 0 taken from the previous phase's prediction for the objects it predicted."""
    prev_case, prev_x, prev_v = previous.phases[-1]
    before = store.object_layout(prev_case.phase.layout[0])
    now = store.object_layout(case.phase.layout[0])
    x, v = case.x.copy(), case.v.copy()
    for name, rows in now.items():
        if name in before:
            x[0, rows], v[0, rows] = prev_x[-1, before[name]], prev_v[-1, before[name]]
    return dataclasses.replace(case, x=x, v=v)


def episode_rollout(reader: CaseReader, eid: str, steps: int, method: Method | None, dt: float) -> Rollout:
    """One rollout of `steps` steps from frame 0 across the episode's phases, each phase the method as Dynamics of
    its case (method None: the recording)."""
    store = reader.store
    out = Rollout(eid, [])
    for phase in episode_phases(store, eid):
        left = steps - sum(len(x) for _, x, _ in out.phases)
        if left < 1 or phase.stop - phase.start < 2:
            break
        case = reader.case(phase, left + 1)
        if method is None:
            out.phases.append((case, case.x[1:].astype(np.float64), case.v[1:].astype(np.float64)))
            continue
        if out.phases:
            case = _carried_start(store, case, out)
        if not np.isfinite(case.x[0]).all():  # diverged before the release: nothing to start from
            nan = np.full((case.steps, *case.x.shape[1:]), np.nan)
            out.phases.append((case, nan, nan.copy()))
            continue
        x, v = predict(method.dynamics(case, dt), case)
        out.phases.append((case, x, v))
    return out


@dataclass
class CaseScores:
    """One method's scores on one case, pooled over its episodes."""

    errors: ErrorTally
    penetration: PenetrationTally
    strain: list[float] = field(default_factory=list)
    divergence: list[int | None] = field(default_factory=list)
    curves: list[StabilityCurve] = field(default_factory=list)

    def add(self, name: str, case_name: str, rollout: Rollout, cfg: EvaluateConfig) -> None:
        parts = []
        for case, x, v in rollout.phases:
            self.errors.add(case_name, x, v, case.x[1:], case.v[1:])
            sd = cloth_signed_distance(case.scene, x, case.link_poses[1:], cfg.contact_band_m)
            self.penetration.add(sd, case.cloth_area)
            parts.append(stability_curve(name, case, x, sd, cfg))
        curve = StabilityCurve(name, case_name, rollout.episode, 0,
                               *(np.concatenate([getattr(c, f) for c in parts])
                                 for f in ("position_mse_m2", "penetration_rate_pct", "max_edge_strain")),
                               _first_divergence(parts))
        self.curves.append(curve)
        self.divergence.append(curve.divergence_step)
        strain = curve.max_edge_strain
        self.strain.append(float(np.nanmax(strain)) if np.isfinite(strain).any() else float("nan"))

    def row(self) -> dict[str, Any]:
        diverged = [d for d in self.divergence if d is not None]
        return {"position_mse_m2": self.errors.summary()["position_mse_m2"],
                "velocity_mse_m2_s2": self.errors.summary()["velocity_mse_m2_s2"],
                "penetration_rate_pct": finite_or_none(self.penetration.rate_pct),
                "max_edge_strain": finite_or_none(max(self.strain)) if all(np.isfinite(self.strain)) else None,
                "divergence_step": min(diverged) if diverged else None, "diverged_episodes": len(diverged),
                "steps": sum(c.steps for c in self.curves)}


def _first_divergence(parts: list[StabilityCurve]) -> int | None:
    """The first divergence step of phases rolled out one after the other (steps counted from frame 0)."""
    offset = 0
    for c in parts:
        if c.divergence_step is not None:
            return offset + c.divergence_step
        offset += c.steps
    return None


def case_scores(reader: CaseReader, cfg: StressConfig, eval_cfg: EvaluateConfig,
                methods: dict[str, Method], dt: float
                ) -> tuple[dict[str, dict[str, CaseScores]], dict[tuple[str, str], Rollout]]:
    """Scores by case and method (ground truth first) and every rollout by (episode, method)."""
    store = reader.store
    scores: dict[str, dict[str, CaseScores]] = {}
    rollouts: dict[tuple[str, str], Rollout] = {}
    episodes = [(store.episode_attrs(e)["case"], e) for e in store.episode_ids]
    for name, eid in tqdm(episodes, desc="stress rollouts", unit="episode"):
        steps = min(cfg.rollout_frames, store.num_frames(eid) - 1)
        by_method = scores.setdefault(name, {})
        for label, method in [(GROUND_TRUTH, None), *methods.items()]:
            rollout = episode_rollout(reader, eid, steps, method, dt)
            tally = by_method.setdefault(label, CaseScores(ErrorTally(cfg.rollout_frames), PenetrationTally(
                eval_cfg.penetration_depth_m, eval_cfg.contact_band_m)))
            tally.add(label, name, rollout, eval_cfg)
            rollouts[(eid, label)] = rollout
    return scores, rollouts


def table_rows(scores: dict[str, dict[str, CaseScores]], tasks: dict[str, str]) -> list[dict[str, Any]]:
    """One row per (case, method), STRESS_HEADER keys; the MSE ratio to REFERENCE where it has one."""
    rows = []
    for name, by_method in scores.items():
        reference = by_method[REFERENCE].row()["position_mse_m2"] if REFERENCE in by_method else None
        for method, s in by_method.items():
            r = s.row()
            mse = r["position_mse_m2"]
            ratio = mse / reference if mse is not None and reference else None
            rows.append({"case": name, "task": tasks[name], "method": method, "episodes": len(s.curves),
                         f"position_mse_vs_{REFERENCE}": ratio, **r})
    return rows


def plot_stress(rows: list[dict[str, Any]], path: str | Path, strain_bound: float) -> Path:
    """Two heatmaps (cases x methods): position MSE relative to constant velocity (log colour, the ratio and
    any divergence step written in each cell) and the largest edge strain."""
    plt = pyplot()
    cases = list(dict.fromkeys(r["case"] for r in rows))
    methods = [m for m in dict.fromkeys(r["method"] for r in rows) if m != GROUND_TRUTH]
    strain_methods = [GROUND_TRUTH, *methods]
    cell = {(r["case"], r["method"]): r for r in rows}
    ratio = np.array([[cell[(c, m)][f"position_mse_vs_{REFERENCE}"] if (c, m) in cell else None for m in methods]
                      for c in cases], dtype=float)
    strain = np.array([[cell[(c, m)]["max_edge_strain"] if (c, m) in cell else None for m in strain_methods]
                       for c in cases], dtype=float)
    fig, axes = plt.subplots(1, 2, figsize=(4.5 + 1.35 * (len(methods) + len(strain_methods)), 1.6 + 0.5 * len(cases)),
                             constrained_layout=True, gridspec_kw={"width_ratios": [len(methods), len(strain_methods)]})
    with np.errstate(divide="ignore", invalid="ignore"):
        log_ratio = np.log10(ratio)
    bound = max(1.0, float(np.nanmax(np.abs(log_ratio)))) if np.isfinite(log_ratio).any() else 1.0
    image = axes[0].imshow(np.ma.masked_invalid(log_ratio), cmap="RdYlGn_r", vmin=-bound, vmax=bound, aspect="auto")
    fig.colorbar(image, ax=axes[0], label=f"log10(position MSE / {REFERENCE})", shrink=0.9)
    for i, c in enumerate(cases):
        for j, m in enumerate(methods):
            r = cell.get((c, m))
            if r is None:
                continue
            text = "n/a" if r[f"position_mse_vs_{REFERENCE}"] is None else f"{r[f'position_mse_vs_{REFERENCE}']:.2f}x"
            if r["divergence_step"] is not None:
                text += f"\ndiv@{r['divergence_step']}"
            axes[0].text(j, i, text, ha="center", va="center", fontsize=7)
    image = axes[1].imshow(np.ma.masked_invalid(strain), cmap="viridis", vmin=0.0,
                           vmax=max(strain_bound, float(np.nanmax(strain)) if np.isfinite(strain).any() else 1.0),
                           aspect="auto")
    fig.colorbar(image, ax=axes[1], label="max edge strain |l/l₀ − 1|", shrink=0.9)
    for i in range(len(cases)):
        for j in range(len(strain_methods)):
            if np.isfinite(strain[i, j]):
                axes[1].text(j, i, f"{strain[i, j]:.2f}", ha="center", va="center", fontsize=7,
                             color="w" if strain[i, j] < 0.5 * strain_bound else "k")
    for ax, names in ((axes[0], methods), (axes[1], strain_methods)):
        ax.set_xticks(range(len(names)), names, rotation=35, ha="right", fontsize=8)
        ax.set_yticks(range(len(cases)), cases, fontsize=8)
    axes[0].set_title(f"position MSE relative to {REFERENCE} (lower is better; div@k: diverged at step k)", fontsize=9)
    axes[1].set_title(f"largest edge strain (divergence above {strain_bound:g})", fontsize=9)
    return save_figure_atomic(fig, path)


def stress(params: dict[str, Any], store: str | Path = STRESS["store"], csv: str | Path = STRESS["csv"],
           png: str | Path = STRESS["png"], curves_csv: str | Path = STRESS["curves"],
           report: str | Path = STRESS["report"], video: str | Path = STRESS["video"],
           sheet: str | Path = STRESS["sheet"], metrics: str | Path = STRESS["metrics"]) -> dict[str, Any]:
    """Simulate (or reuse) the stress ground truth, roll every method out on it, write the table, figure,
    per-step curves, side-by-side video and contact sheet, and the report (returned)."""
    cfg = load_section(params, "stress", StressConfig)
    eval_cfg = load_section(params, "evaluate", EvaluateConfig)
    scene_cfg = load_section(params, "scene", SceneConfig)
    model_cfg = load_section(params, "model", ModelConfig)
    train_cfg = load_section(params, "train", TrainConfig)
    started = time.perf_counter()
    torch.manual_seed(cfg.seed)
    device = resolve_device(cfg.device, "stress.device")
    methods, skipped = load_methods(eval_cfg, train_cfg, model_cfg.tag_scale, device, scene_cfg,
                                    load_section(params, "sim", SimConfig))
    unknown = sorted(set(cfg.methods or ()) - set(eval_cfg.methods))
    if unknown:
        raise ValueError(f"stress.methods {unknown} are not evaluate.methods entries {sorted(eval_cfg.methods)}")
    for name in [n for n in methods if cfg.methods is not None and n not in cfg.methods]:
        del methods[name]
        skipped[name] = "not in stress.methods"
    for name in [n for n, m in methods.items() if isinstance(m, NewtonMethod)]:  # as evaluate's long rollouts
        del methods[name]
        skipped[name] = "a Newton setting: not rolled out (the stress ground truth is Newton, with per-case overrides)"
    missing = [m for m in (cfg.video.method,) if m not in methods]
    if missing:
        raise ValueError(f"stress.video.method {cfg.video.method!r} is not an available evaluate method "
                         f"(available: {sorted(methods)}; skipped: {sorted(skipped)})")
    truth_store, truth = ground_truth(params, cfg, store)
    simulated = time.perf_counter()
    dt = float(truth_store.dt)
    reader = CaseReader(truth_store, scene_cfg, model_cfg.tag_scale, device)
    scores, rollouts = case_scores(reader, cfg, eval_cfg, methods, dt)
    tasks = {n: cfg.case_task(n) for n in cfg.cases}
    rows = table_rows(scores, tasks)
    write_csv_atomic(csv, STRESS_HEADER, [["" if r[k] is None else r[k] for k in STRESS_HEADER] for r in rows])
    write_csv_atomic(curves_csv, CSV_HEADER,
                     csv_rows([c for by_method in scores.values() for s in by_method.values() for c in s.curves], dt))
    plot_stress(rows, png, eval_cfg.divergence_strain)
    rolled = time.perf_counter()
    video_report = side_by_side_video(truth_store, scene_cfg, cfg, rollouts, rows, metrics, video, sheet)
    episodes = {e: {k: truth_store.episode_attrs(e).get(k) for k in
                    ("case", "task", "seed", "cell", "speed", "amplitude", "accepted", "first_failure",
                     "failure_frame", "peak_tcp_speed_m_s", "handoff")} | {"frames": truth_store.num_frames(e)}
                for e in truth_store.episode_ids}
    result = {
        "cases": {n: {"task": tasks[n], "overrides": {**cfg.overrides, **cfg.cases[n].overrides}} for n in cfg.cases},
        "episodes": episodes,
        "table": rows,
        "skipped": skipped,
        "models": model_records(eval_cfg, methods),
        "ground_truth": truth,
        "rollout_frames": cfg.rollout_frames,
        "divergence": {"strain": eval_cfg.divergence_strain, "penetration_pct": eval_cfg.divergence_penetration_pct},
        "penetration": {"depth_m": eval_cfg.penetration_depth_m, "contact_band_m": eval_cfg.contact_band_m},
        "video": video_report,
        "params_hash": params_hash(params, SECTIONS),
        "wall_s": {"total": time.perf_counter() - started, "ground_truth": simulated - started,
                   "rollouts": rolled - simulated, "video": time.perf_counter() - rolled},
        "environment": environment_info(str(device)),
        **smoke_label(params, "stress"),
    }
    write_json_atomic(report, result)
    return result


def stress_summary(r: dict[str, Any]) -> str:
    """The lines `python -m stages.stress` prints: one per case and method, then the video."""
    def fmt(value: float | None, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    truth = r["ground_truth"]
    lines = [f"stress: {len(r['episodes'])} ground-truth episodes "
             f"({'reused' if truth['reused'] else 'simulated'}), {r['wall_s']['total']:.0f} s"]
    lines += [f"  {row['case']:20s} {row['method']:28s} x MSE {fmt(row['position_mse_m2'], '.3e')} m²  "
              f"vs CV {fmt(row['position_mse_vs_constant_velocity'], '.2f')}  "
              f"penetration {fmt(row['penetration_rate_pct'], '.2f')} %  strain {fmt(row['max_edge_strain'], '.2f')}  "
              f"diverged at {fmt(row['divergence_step'], 'd')}" for row in r["table"]]
    lines.append(f"  video: {r['video']['video']} ({r['video']['frames']} frames: {', '.join(r['video']['panels'])})")
    return "\n".join(lines)
