"""How fine a bag the scene needs: the same task plans in Newton at several bag resolutions, each against the finest
that runs.

    python -m benchmarks.resolution --params params.yaml [--set key=value ...] [--task lift_handle] [--plans 64]
        --resolution 300 --resolution 1200 --resolution "5000:sim.bag.particle_radius_m=0.002,..."
        [--points 256] [--noise-m 1e-4] [--image-plans 4] [--image-frames 6] [--image-px 64]
        [--agreement 0.95] --out reports/gpu/resolution_<device>.json     (also the .md and a .png)

A resolution is `scene.bag.target_vertices` with optional overrides of its own (contact radii, iterations: what must
scale with the edge length). The same episode specs (drawn once, as the simulate stage draws them) are reset, settled,
planned and replayed in Newton at each resolution, `sim.worlds` at a time. Per resolution:
- Newton's cost: rollout seconds per episode, and reset + planning seconds per episode;
- the verdicts of the source data's checks and the task's own; `stable` when no episode blows up, goes non-finite or
  self-intersects;
- the bag's edge stretch over the lifted frames (benchmarks.fabric_stretch.BagStretch);
- common surface points: `--points` points sampled (seeded, area-weighted) on the finest resolution's rest surface,
  carried by every resolution's rest mesh (wc.scene.resample.surface_map), so two resolutions' trajectories compare;
- its noise floor: Newton replays the plans again in reverse batch order from frame-0 positions + N(0, noise^2), and the
  common points' RMS distance between the two replays is how far Newton disagrees with itself there;
- top and wrist images of a few plans at a few frames (`--image-*`), rendered from its own mesh.
Against the reference (the finest stable resolution): verdict agreement on the plans both could plan, the common
points' RMS distance (per plan over their common frames, then the mean), the mean absolute image difference per camera.
`needed_vertices`: the coarsest stable resolution whose verdicts agree >= --agreement with the reference and whose
distance is within the reference's noise floor. Rows are written as they finish; the comparison once all have.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from benchmarks.fabric_stretch import BagStretch, parse_setting, replay_batches
from benchmarks.newton_convergence import draw_specs
from benchmarks.resolution_report import chart, markdown
from wc.agent.replay import plan_specs, same_verdict, share
from wc.agent.runner import build_task_world
from wc.config import add_params_arguments, load_section, read_params
from wc.devices import resolve_warp_device
from wc.render.geometry import scene_geometry
from wc.render.renderer import EpisodeRenderer
from wc.render.rig import render_cameras
from wc.reports import environment_info, write_report_atomic
from wc.scene.config import SceneConfig
from wc.scene.resample import SurfaceMap, surface_map
from wc.scene.scene import build_scene
from wc.sim.config import SimConfig
from wc.tasks.base import EpisodeSpec, get_task
from wc.validate.config import ValidateConfig

UNSTABLE = ("blow_up", "non_finite", "self_intersection")
CAMERAS = ("top", "wrist")


def parse_resolution(text: str) -> tuple[int, list[str]]:
    """'1200' or '5000:a.b=1,c=2' -> (target vertices, overrides)."""
    head, _, rest = text.partition(":")
    try:
        vertices = int(head)
    except ValueError:
        vertices = 0
    if vertices < 4:
        raise argparse.ArgumentTypeError(f"a resolution is VERTICES[:key=value,...] with VERTICES >= 4, got {text!r}")
    return vertices, parse_setting(rest) if rest.strip() else []


def common_points(params: dict[str, Any], count: int, seed: int) -> np.ndarray:
    """`count` points (M, 3) sampled, area-weighted and seeded, on the rest surface of the params' bag."""
    bag = build_scene(load_section(params, "scene", SceneConfig)).objects["bag"]
    mesh = trimesh.Trimesh(bag.vertices, bag.faces, process=False)
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, np.float64)


class Measured:
    """One resolution's replays, reduced to what the comparison needs: per spec seed its verdict, the common points'
    trajectory (T, M, 3), its repeat's, and its rendered frames."""

    def __init__(self) -> None:
        self.verdicts: dict[int, str] = {}
        self.points: dict[int, np.ndarray] = {}
        self.repeat_points: dict[int, np.ndarray] = {}
        self.images: dict[int, dict[str, np.ndarray]] = {}


def measure(params: dict[str, Any], overrides: list[str], task_name: str, specs: list[EpisodeSpec],
            points: np.ndarray, args: argparse.Namespace) -> tuple[dict[str, Any], Measured]:
    """One resolution's row (`overrides`: its own, recorded) and its reduced replays."""
    sim_cfg, validate_cfg = load_section(params, "sim", SimConfig), load_section(params, "validate", ValidateConfig)
    world = build_task_world(load_section(params, "scene", SceneConfig), sim_cfg, get_task(task_name, params))
    stretch = BagStretch(world)  # names a task without a bag
    bag = world.scene.objects["bag"]
    carry: SurfaceMap = surface_map(bag.vertices, bag.faces, points)
    rows = world.scene.vertex_slices()["bag"]
    started = time.perf_counter()
    plans = plan_specs(world, specs, sim_cfg.worlds)
    plan_s = time.perf_counter() - started
    out, rollout_s = Measured(), 0.0
    renderer = None
    if args.image_plans > 0:
        cams = render_cameras(load_section(params, "scene", SceneConfig).cameras, CAMERAS, args.image_px, args.image_px)
        renderer = EpisodeRenderer(scene_geometry(world.scene), cams, resolve_warp_device(sim_cfg.device, "sim.device"),
                                   batch=args.image_frames, shadows=False)
    for batch, replays, seconds in replay_batches(world, plans, validate_cfg, sim_cfg.frame_dt_s,
                                                  desc=f"{len(bag.vertices)} vertices"):
        rollout_s += seconds
        for plan, r in zip(batch, replays):
            seed = plan.spec.seed
            out.verdicts[seed] = r.verdict
            out.points[seed] = carry.apply(r.x[:, rows]).astype(np.float32)
            stretch.add(r.x)
            if renderer is not None and len(out.images) < args.image_plans:
                at = frame_indices(len(r.x), args.image_frames)
                out.images[seed] = renderer.render(r.x[at], world.scene.link_poses(plan.action)[at], "resolution")
    if args.noise_m > 0:  # Newton against itself: reversed batch order, perturbed frame-0 positions
        for batch, replays, _ in replay_batches(world, list(reversed(plans)), validate_cfg, sim_cfg.frame_dt_s,
                                                args.noise_m, seed=args.seed + 1, desc="again"):
            for plan, r in zip(batch, replays):
                out.repeat_points[plan.spec.seed] = carry.apply(r.x[:, rows]).astype(np.float32)
    verdicts = list(out.verdicts.values())
    lifted = stretch.summaries(0.05)["lifted"]["all"] or {}
    row = {"vertices": len(bag.vertices), "target_vertices": int(params["scene"]["bag"]["target_vertices"]),
           "overrides": overrides, "plans": len(plans),
           "unplannable": len(specs) - len(plans), "iterations": sim_cfg.iterations, "substeps": sim_cfg.substeps,
           "worlds": sim_cfg.worlds, "newton_s_per_episode": rollout_s / max(1, len(plans)),
           "plan_s_per_episode": plan_s / max(1, len(plans)),
           "verdicts": {v: verdicts.count(v) for v in sorted(set(verdicts))},
           "accepted": share([v == "accepted" for v in verdicts]),
           "stable": bool(plans) and not any(v in UNSTABLE for v in verdicts),
           "p99_stretch": lifted.get("p99"), "max_stretch": lifted.get("max"),
           "noise_floor_mm": mean_distance_mm(out.points, out.repeat_points)}
    return row, out


def frame_indices(frames: int, count: int) -> np.ndarray:
    """`count` frames spread over an episode of `frames`, first and last included."""
    return np.unique(np.linspace(0, frames - 1, max(1, count)).round().astype(int))


def mean_distance_mm(a: dict[int, np.ndarray], b: dict[int, np.ndarray]) -> float | None:
    """Mean over the seeds in both of the RMS point distance over their common frames [mm]; None if none."""
    seeds = sorted(set(a) & set(b))
    if not seeds:
        return None
    rms = []
    for s in seeds:
        t = min(len(a[s]), len(b[s]))
        d = np.linalg.norm(a[s][:t].astype(np.float64) - b[s][:t], axis=-1)
        rms.append(np.sqrt(np.nanmean(np.square(d))) if np.isfinite(d).any() else np.inf)
    return 1e3 * float(np.mean(rms))


def compare(rows: list[dict[str, Any]], measured: list[Measured], agreement: float) -> int | None:
    """Fill each row's figures against the reference (the finest stable resolution); the needed vertices."""
    stable = [i for i, r in enumerate(rows) if r["stable"]]
    if not stable:
        for r in rows:
            r.update(reference=False, verdict_agreement=None, rms_mm=None, image_diff=None)
        return None
    ref = max(stable, key=lambda i: rows[i]["vertices"])
    ref_m, floor = measured[ref], rows[ref]["noise_floor_mm"]
    for r, m in zip(rows, measured):
        seeds = sorted(set(m.verdicts) & set(ref_m.verdicts))
        r["reference"] = r is rows[ref]
        r["verdict_agreement"] = share([same_verdict(m.verdicts[s], ref_m.verdicts[s]) for s in seeds])
        r["rms_mm"] = mean_distance_mm(m.points, ref_m.points)
        shared = sorted(set(m.images) & set(ref_m.images))
        r["image_diff"] = {c: float(np.mean([np.abs(m.images[s][c].astype(np.int16) - ref_m.images[s][c]).mean()
                                             / 255.0 for s in shared])) if shared else None for c in CAMERAS}
        r["within_noise"] = None if floor is None or r["rms_mm"] is None else r["rms_mm"] <= floor
    for r in sorted((rows[i] for i in stable), key=lambda r: r["vertices"]):
        agrees = r["verdict_agreement"] is not None and r["verdict_agreement"] >= agreement
        if agrees and (r["reference"] or r["within_noise"]):
            return int(r["vertices"])
    return None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--task", default="lift_handle")
    parser.add_argument("--plans", type=int, default=64, help="episode specs, the same at every resolution")
    parser.add_argument("--resolution", type=parse_resolution, action="append", required=True,
                        help="VERTICES[:key=value,...] (repeat per resolution)")
    parser.add_argument("--points", type=int, default=256, help="common surface points")
    parser.add_argument("--noise-m", type=float, default=1e-4, help="frame-0 noise of Newton's repeat (0: none)")
    parser.add_argument("--image-plans", type=int, default=4, help="plans rendered per resolution (0: none)")
    parser.add_argument("--image-frames", type=int, default=6, help="frames rendered per plan")
    parser.add_argument("--image-px", type=int, default=64, help="rendered image side [px]")
    parser.add_argument("--agreement", type=float, default=0.95, help="verdict agreement the needed resolution meets")
    parser.add_argument("--seed", type=int, default=0, help="agent seed of the specs, and of the samples")
    parser.add_argument("--out", default="reports/resolution.json")
    args = parser.parse_args(argv)
    if min(args.plans, args.points, args.image_frames, args.image_px) < 1 or args.image_plans < 0 \
            or not args.noise_m >= 0 or not 0 < args.agreement <= 1:
        parser.error("--plans, --points, --image-frames, --image-px must be >= 1, --image-plans >= 0, --noise-m >= 0 "
                     "and 0 < --agreement <= 1")
    resolutions = sorted(args.resolution)
    settings = []
    for vertices, overrides in resolutions:  # every resolution's params and bag made before any runs: a bad one fails now
        params = read_params(args.params, [*args.overrides, f"scene.bag.target_vertices={vertices}", *overrides])
        build_scene(load_section(params, "scene", SceneConfig))
        settings.append((overrides, params))
    base = read_params(args.params, args.overrides)
    specs = draw_specs(base, args.task, args.plans, args.seed)
    points = common_points(settings[-1][1], args.points, args.seed)
    out = Path(args.out)
    report: dict[str, Any] = {
        "benchmark": "resolution", "task": args.task, "plans": args.plans, "points": args.points,
        "noise_m": args.noise_m, "agreement_needed": args.agreement, "command": " ".join(sys.argv),
        "params": args.params, "overrides": args.overrides, "seed": args.seed,
        "environment": environment_info(resolve_warp_device(base["sim"]["device"], "sim.device")),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "rows": [], "needed_vertices": None}
    measured = []
    for overrides, params in settings:
        row, m = measure(params, overrides, args.task, specs, points, args)
        report["rows"].append(row)
        measured.append(m)
        print(f"{row['vertices']} vertices: {row['verdicts']}, {row['newton_s_per_episode']:.2f} s per episode, "
              f"noise floor {row['noise_floor_mm']} mm", flush=True)
        write_report_atomic(out, report, markdown(report))
    report["needed_vertices"] = compare(report["rows"], measured, args.agreement)
    report["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    write_report_atomic(out, report, markdown(report))
    chart(report, out.with_suffix(".png"))
    print(markdown(report))


if __name__ == "__main__":
    main()
