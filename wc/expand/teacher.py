"""Teacher check: generated episodes replayed in Newton, the source simulator, from the same plan.

A generated episode's plan is its frame-0 state and its action sequence. Newton rolls the plan out from that
state and the source data's checks judge both rollouts, so the report says how often Newton agrees with what
WorldContact accepted (`precision`) and how far the two trajectories drift apart per frame. Only accepted
episodes are stored by the expand stage, so on its store this measures precision, not recall.

    python -m stages.teacher_check [--params params.yaml] [--store data/expanded/trajectories.zarr]
        [--report reports/teacher_check.json] [--limit N]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from wc.agent.runner import build_task_world, execute, judge
from wc.config import add_params_arguments, load_section, read_params
from wc.data.store import TrajectoryStore
from wc.dynamics import ObjectState
from wc.expand.config import ExpandConfig
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.tasks.base import EpisodeSpec, get_task
from wc.validate.config import ValidateConfig


def teacher_check(params: dict[str, Any], store_path: str | Path, limit: int | None = None) -> dict[str, Any]:
    """Replay the generated episodes of `expand.task` in `store_path` in Newton; per plan both verdicts and the
    per-frame RMS vertex distance between the two rollouts."""
    store_path = Path(store_path)
    if not store_path.exists():
        raise FileNotFoundError(f"teacher check: no generated store at {store_path} (run the expand stage first)")
    cfg = load_section(params, "expand", ExpandConfig)
    sim_cfg = load_section(params, "sim", SimConfig)
    validate_cfg = load_section(params, "validate", ValidateConfig)
    store = TrajectoryStore(store_path)
    episodes = store.episodes_where(task=cfg.task, source="worldcontact")[:limit]
    if not episodes:  # nothing generated passed: nothing to check, and the report says so
        return {"task": cfg.task, "store": str(store_path), "plans": 0, "agreement": None, "precision": None,
                "confusion": {}, "mean_rms_error_m": None, "episodes": [], "wall_s": 0.0,
                "note": f"no generated {cfg.task!r} episode in the store", "environment": environment_info("cpu")}
    task = get_task(cfg.task, params)
    world = build_task_world(load_section(params, "scene", SceneConfig), sim_cfg, task)
    started, plans = time.perf_counter(), []
    for eid in episodes:
        attrs = store.episode_attrs(eid)
        ep = store.read_episode(eid, ("x", "v", "action"))
        spec = EpisodeSpec(task.name, int(attrs["seed"]), int(attrs["cell"]), float(attrs["speed"]),
                           float(attrs["amplitude"]))
        (x, v), = execute(world, [ObjectState(ep["x"][0], ep["v"][0])], [ep["action"]], None)[0]
        newton = judge(world, spec, x, v, ep["action"], world.scene.link_poses(ep["action"]), validate_cfg,
                       sim_cfg.frame_dt_s)
        frames = min(len(x), len(ep["x"]))
        rms = np.sqrt(np.square(x[:frames] - ep["x"][:frames]).sum(-1).mean(-1))  # (T,) m
        plans.append({"episode": eid, "parent": attrs.get("parent"), "worldcontact": "accepted" if attrs["accepted"] else str(attrs["first_failure"]),
                      "newton": "accepted" if newton is None else newton[0], "newton_failure_frame": None if newton is None else int(newton[1]),
                      "rms_error_m": [float(e) for e in rms], "final_rms_error_m": float(rms[-1]),
                      "mean_rms_error_m": float(rms.mean())})
    accepted = [p for p in plans if p["worldcontact"] == "accepted"]
    agree = sum(p["worldcontact"] == p["newton"] or "accepted" not in (p["worldcontact"], p["newton"]) for p in plans)
    confusion: dict[str, int] = {}
    for p in plans:
        key = f"worldcontact {p['worldcontact']} / newton {p['newton']}"
        confusion[key] = confusion.get(key, 0) + 1
    return {"task": cfg.task, "store": str(store_path), "plans": len(plans), "agreement": agree / len(plans),
            "precision": (sum(p["newton"] == "accepted" for p in accepted) / len(accepted)) if accepted else None,
            "confusion": confusion, "mean_rms_error_m": float(np.mean([p["mean_rms_error_m"] for p in plans])),
            "episodes": plans, "wall_s": time.perf_counter() - started,
            "note": "the expand stage stores accepted episodes only: precision, not recall",
            "environment": environment_info(sim_cfg.device)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--store", default="data/expanded/trajectories.zarr")
    parser.add_argument("--report", default="reports/teacher_check.json")
    parser.add_argument("--limit", type=int, default=None, help="check the first N generated episodes only")
    args = parser.parse_args(argv)
    report = teacher_check(read_params(args.params, args.overrides), args.store, args.limit)
    write_json_atomic(args.report, report)
    if not report["plans"]:
        print(f"teacher check: {report['note']}")
        return
    print(f"teacher check: {report['plans']} plans, agreement {report['agreement']:.2f}, precision "
          f"{report['precision']}, mean RMS {report['mean_rms_error_m'] * 1000:.1f} mm; {report['confusion']}")


if __name__ == "__main__":
    main()
