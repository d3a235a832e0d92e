"""Teacher check: generated episodes replayed in Newton, the source simulator, from the same plan.

A generated episode's plan is its frame-0 state and its action sequence. Newton rolls the plans out from those
states, `sim.worlds` at a time, and the source data's checks judge both rollouts, so the report says how often the
two verdicts agree, how often Newton accepts what WorldContact accepted (`precision`), how often WorldContact
accepted what Newton accepts (`recall`: needs the rejected episodes, which the expand stage keeps in a second
store) and how far the two trajectories drift apart per frame.

Newton against itself (`newton_perturb_m`, wc/agent/replay.py): for each listed scale s, Newton replays every plan
once more, in another batch order (VBD's few iterations do not converge, so a plan's neighbours in the batch move it
slightly) and from its frame-0 positions with N(0, s^2) added to each coordinate. How often Newton's verdict then
stays the same is the agreement a perfect model could reach on these plans: the teacher check's ceiling.

    python -m stages.teacher_check [--params params.yaml] [--store data/expanded/trajectories.zarr]
        [--rejected data/expanded/rejected.zarr] [--report reports/teacher_check.json] [--limit N]
        [--newton-perturb-m S [S ...]]
"""

from __future__ import annotations

import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from wc.agent.replay import Plan, Replay, replay, same_verdict, self_agreement, share
from wc.agent.runner import build_task_world
from wc.config import load_section
from wc.data.store import TrajectoryStore
from wc.expand.config import ExpandConfig
from wc.paths import TEACHER_CHECK
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.smoke import smoke_label
from wc.tasks.base import EpisodeSpec, get_task
from wc.validate.config import ValidateConfig


def _generated(path: Path, task: str, limit: int | None) -> list[tuple[TrajectoryStore, str]]:
    """(store, episode id) of the first `limit` generated episodes of `task` in the store at `path`."""
    if not path.exists():
        raise FileNotFoundError(f"teacher check: no generated store at {path} (run the expand stage first)")
    store = TrajectoryStore(path)
    return [(store, eid) for eid in store.episodes_where(task=task, source="worldcontact")[:limit]]


def _plan(store: TrajectoryStore, eid: str, task: str) -> Plan:
    """A generated episode's plan: its frame-0 state and actions; its trajectory, the replay's reference, is read when
    the plan's batch is judged (all of them at once would hold ~2 GB at paper scale)."""
    first, attrs = store.read_window(eid, 0, 1, ("x", "v")), store.episode_attrs(eid)
    spec = EpisodeSpec(task, int(attrs["seed"]), int(attrs["cell"]), float(attrs["speed"]),
                       float(attrs["amplitude"]))
    return Plan(spec, first["x"][0], first["v"][0], store.read_episode(eid, ("action",))["action"],
                reference_x=lambda: store.read_episode(eid, ("x",))["x"])


def _checked(store: TrajectoryStore, eid: str, newton: Replay) -> dict[str, Any]:
    """One plan's row of the report: both verdicts and the per-frame RMS distance between the two rollouts."""
    attrs, rms = store.episode_attrs(eid), newton.rms_error_m
    return {"episode": eid, "store": str(store.path), "parent": attrs.get("parent"),
            "worldcontact": "accepted" if attrs["accepted"] else str(attrs["first_failure"]),
            "newton": newton.verdict, "newton_failure_frame": newton.failure_frame, "newton_detail": newton.detail,
            "rms_error_m": [float(e) for e in rms], "final_rms_error_m": float(rms[-1]),
            "mean_rms_error_m": float(rms.mean())}


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def teacher_check(params: dict[str, Any], store_path: str | Path, limit: int | None = None,
                  rejected_path: str | Path | None = None, newton_perturb_m: list[float] | None = None) -> dict[str, Any]:
    """Replay the generated episodes of `expand.task` (the first `limit` of each store: the accepted ones in
    `store_path`, the rejected ones in `rejected_path` if given) in Newton; per plan both verdicts and the
    per-frame RMS vertex distance between the two rollouts; agreement, precision, recall and the confusion table;
    `constant_agreement`, what a check that gave every plan Newton's more common verdict would agree on (a teacher that
    accepts nearly every plan makes agreement cheap);
    with `newton_perturb_m`, Newton's agreement with itself (the module docstring)."""
    if any(not s >= 0 for s in newton_perturb_m or []):
        raise ValueError(f"teacher check: newton_perturb_m must be scales >= 0 m, got {newton_perturb_m}")
    cfg = load_section(params, "expand", ExpandConfig)
    sim_cfg = load_section(params, "sim", SimConfig)
    validate_cfg = load_section(params, "validate", ValidateConfig)
    plans = _generated(Path(store_path), cfg.task, limit)
    if rejected_path is not None:
        plans += _generated(Path(rejected_path), cfg.task, limit)
    base = {"task": cfg.task, "store": str(store_path), "rejected_store": None if rejected_path is None else str(rejected_path),
            # the weights that generated the plans (expand records their SHA-256 in each episode; None: not recorded)
            "model_sha256": sorted({s.episode_attrs(e).get("model_sha256") or "not recorded" for s, e in plans})}
    if not plans:  # nothing generated: nothing to check, and the report says so
        return {**base, "plans": 0, "agreement": None, "precision": None, "recall": None, "confusion": {},
                "mean_rms_error_m": None, "episodes": [], "wall_s": 0.0,
                "note": f"no generated {cfg.task!r} episode in the stores", "environment": environment_info("cpu")}
    world = build_task_world(load_section(params, "scene", SceneConfig), sim_cfg, get_task(cfg.task, params))
    started = time.perf_counter()
    replays = [_plan(store, eid, cfg.task) for store, eid in plans]
    newton = replay(world, replays, validate_cfg, sim_cfg.frame_dt_s, keep_x=bool(newton_perturb_m),
                    desc="teacher check")
    checked = [_checked(store, eid, r) for (store, eid), r in zip(plans, newton)]
    self_check, repeats = self_agreement(world, replays, newton, validate_cfg, sim_cfg.frame_dt_s,
                                         newton_perturb_m or [], cfg.seed)
    for row, plan_repeats in zip(checked, repeats):
        if plan_repeats:
            row["newton_repeats"] = plan_repeats
    newton_accepts = share([p["newton"] == "accepted" for p in checked])
    confusion: dict[str, int] = {}
    for p in checked:
        key = f"worldcontact {p['worldcontact']} / newton {p['newton']}"
        confusion[key] = confusion.get(key, 0) + 1
    return {**base, "plans": len(checked),
            "agreement": share([same_verdict(p["worldcontact"], p["newton"]) for p in checked]),
            "newton_self_agreement": self_check, "newton_accepts": newton_accepts,
            "constant_agreement": max(newton_accepts, 1.0 - newton_accepts),
            "precision": share([p["newton"] == "accepted" for p in checked if p["worldcontact"] == "accepted"]),
            "recall": share([p["worldcontact"] == "accepted" for p in checked if p["newton"] == "accepted"])
            if rejected_path is not None else None,
            "confusion": confusion, "mean_rms_error_m": float(np.mean([p["mean_rms_error_m"] for p in checked])),
            "accepted_mean_rms_error_m": _mean([p["mean_rms_error_m"] for p in checked
                                               if p["worldcontact"] == "accepted"]),
            "rejected_mean_rms_error_m": _mean([p["mean_rms_error_m"] for p in checked
                                               if p["worldcontact"] != "accepted"]),
            "episodes": checked, "wall_s": time.perf_counter() - started, "worlds": sim_cfg.worlds,
            "note": ("accepted and rejected plans: precision and recall" if rejected_path is not None else
                     "accepted plans only: precision, not recall"),
            "environment": environment_info(sim_cfg.device)}


def expansion_weighted(confusion: dict[str, int], accepted: int, rejected: int) -> dict[str, float | int | None]:
    """The check's figures for the whole expansion rather than its sample. A check of the first N accepted and the
    first N rejected plans over-represents the rejected ones when the expansion accepts most plans; here each stratum
    of `confusion` (WorldContact accepted, WorldContact rejected) counts as many episodes as it stands for (`accepted`,
    `rejected`: the expansion's generated episodes of each). None where a stratum with episodes was not sampled."""
    if min(accepted, rejected) < 0:
        raise ValueError(f"teacher check: episode counts must be >= 0, got accepted {accepted}, rejected {rejected}")
    plans = {"accepted": Counter(), "rejected": Counter()}  # per stratum: plans, Newton accepts, verdicts agree
    for key, count in confusion.items():
        ours, newton = (part.split(" ", 1)[1] for part in key.split(" / "))
        stratum = plans["accepted" if ours == "accepted" else "rejected"]
        stratum["plans"] += count
        stratum["newton_accepts"] += count * (newton == "accepted")
        stratum["agree"] += count * same_verdict(ours, newton)
    episodes = {"accepted": accepted, "rejected": rejected}
    out: dict[str, float | int | None] = {"accepted_episodes": accepted, "rejected_episodes": rejected,
                                          "agreement": None, "newton_accepts": None, "recall": None}
    if not accepted + rejected or any(episodes[k] and not plans[k]["plans"] for k in plans):
        return out

    def expected(stratum: str, what: str) -> float:
        """Episodes of the stratum expected to be `what`, at its sample's rate."""
        n = plans[stratum]["plans"]
        return episodes[stratum] * plans[stratum][what] / n if n else 0.0

    newton_yes = {k: expected(k, "newton_accepts") for k in plans}
    both, total = sum(newton_yes.values()), accepted + rejected
    return out | {"agreement": sum(expected(k, "agree") for k in plans) / total, "newton_accepts": both / total,
                  "recall": newton_yes["accepted"] / both if both else None}


def run(params: dict[str, Any], store: str | Path = TEACHER_CHECK["store"],
        report: str | Path = TEACHER_CHECK["report"], rejected: str | Path | None = TEACHER_CHECK["rejected"],
        limit: int | None = None, newton_perturb_m: list[float] | None = None) -> dict[str, Any]:
    """`teacher_check` of the stores `store` and `rejected` (None: accepted plans only), written to `report`."""
    result = teacher_check(params, store, limit, rejected, newton_perturb_m) | smoke_label(params, "teacher_check")
    write_json_atomic(report, result)
    return result


def teacher_check_summary(report: dict[str, Any]) -> str:
    """The line `python -m stages.teacher_check` prints."""
    if not report["plans"]:
        return f"teacher check: {report['note']}"
    return (f"teacher check: {report['plans']} plans, agreement {report['agreement']:.2f} (one verdict for all: "
            f"{report['constant_agreement']:.2f}), precision "
            f"{report['precision']}, recall {report['recall']}, mean RMS {report['mean_rms_error_m'] * 1000:.1f} mm; "
            f"{report['confusion']}" + "".join(f"; Newton against itself at {r['perturb_m']:g} m: agreement "
                                               f"{r['agreement']:.2f}" for r in report.get("newton_self_agreement", [])))
