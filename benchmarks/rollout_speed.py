"""WorldContact rollout speed beside the Newton source simulator, in one process on one device.

    python -m benchmarks.rollout_speed --params params/gpu.yaml --tag h100
        [--store PATH | --synthetic carry] [--checkpoint models/worldcontact/model.safetensors]
        [--frames 20] [--batches 8,32] [--skins 0.001,0.002,0.004] [--newton-worlds 8] [--newton-frames 10]
        [--skip-newton] [--newton-reference reports/sim_speed_h100.json] [--budget-s 540]
    -> reports/rollout_speed_<tag>.json (rewritten after every row) + reports/rollout_speed_<tag>.md

The episode is --episode, else the store's first lift_handle episode, else its first. Rows, in this order (each catches CUDA out-of-memory and goes on; a row that would start after
--budget-s of wall time is recorded as skipped):
1. single rollouts (B = 1) of the store's first episode, `--frames` frames, median of `--repeats`:
   fp32 reference; bf16 autocast (CUDA); bf16 (fp32 on CPU) + Verlet-skin neighbour reuse per --skins;
   each with ms/step, simulated s / wall s, the neighbour searches and reuses, and its position MSE
   against the fp32 reference rollout and against the stored frames (relative to the reference's);
2. batched rollouts (B per --batches) without and with the fastest single row's skin: aggregate s/s;
3. a per-part profile of the fastest variant (benchmarks.rollout_profile), the topology projection's
   time per step, and the time per optimisation step at W = --train-window (benchmarks.model_speed);
4. Newton (benchmarks.sim_speed.measure): one world, then --newton-worlds worlds, timed over
   --newton-frames frames of a lift episode from the gripper's closing frame.
Ratios use the Newton rows of this run; without them (--skip-newton, or over budget) the ratio columns
use --newton-reference (a sim_speed report) and say so. The model has random weights unless
--checkpoint is given (speed does not depend on them; the MSE rows are then only a consistency check).
Without --store, a schema-valid synthetic episode (tests.synthetic_store, kind --synthetic) of the
params' scene is written to a temporary directory: no simulation needed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from benchmarks.model_speed import episode_model, sync, time_training
from benchmarks.rollout_profile import profile
from benchmarks.rollout_speed_report import markdown, targets_met
from benchmarks.sim_speed import TASK, measure
from wc.config import add_params_arguments, load_section, read_params
from wc.data.store import TrajectoryStore
from wc.model.config import ModelConfig
from wc.model.neighbor_cache import NeighborCache
from wc.model.rollout import rollout
from wc.model.worldcontact import WorldContact
from wc.reports import environment_info, write_json_atomic
from wc.train.checkpoint import load_model
from wc.train.config import TrainConfig
from wc.train.data import read_phase_window


def _floats(text: str) -> list[float]:
    return [float(t) for t in text.split(",") if t.strip()]


def _ints(text: str) -> list[int]:
    return [int(t) for t in text.split(",") if t.strip()]


@torch.no_grad()
def time_variant(model: WorldContact, layout: Any, a: dict[str, torch.Tensor], dt: float, frames: int, batch: int,
                 bf16: bool, skin_m: float, repeats: int, device: torch.device,
                 projection: Any = None) -> tuple[dict[str, Any], torch.Tensor]:
    """One timed variant: median wall time of `repeats` rollouts of `frames` frames of `batch` copies of the
    episode (with the topology projection P after every step when given, as a projection-stage checkpoint
    rolls out); each rollout starts with an empty neighbour cache. Returns the row and the last rollout's x
    (batch, frames, N, 3)."""
    x0 = a["x"][0].expand(batch, -1, -1).contiguous()
    v0 = a["v"][0].expand(batch, -1, -1).contiguous()
    poses = a["poses"][: frames + 1][None].expand(batch, -1, -1, -1).contiguous()
    autocast = torch.autocast("cuda", dtype=torch.bfloat16) if bf16 and device.type == "cuda" else nullcontext()

    def run(p: torch.Tensor) -> tuple[torch.Tensor, NeighborCache | None]:
        cache = NeighborCache(skin_m) if skin_m > 0 else None
        with autocast:
            xs, _ = rollout(model, layout, x0, v0, p, dt, projection, neighbor_skin_m=0.0, neighbors=cache)
        return xs, cache

    run(poses[:, :3])  # warm-up: allocations, kernel compilation
    walls = []
    for _ in range(repeats):
        sync(device)
        t = time.perf_counter()
        xs, cache = run(poses)
        sync(device)
        walls.append(time.perf_counter() - t)
    wall = statistics.median(walls)
    row = {"batch": batch, "frames": frames, "bf16": bf16 and device.type == "cuda", "skin_m": skin_m,
           "wall_s": walls, "ms_per_step_median": 1e3 * wall / frames,
           "simulated_s_per_wall_s": frames * dt / wall, "simulated_s_per_wall_s_aggregate": batch * frames * dt / wall,
           "neighbour_searches": dict(cache.builds) if cache else "every step",
           "neighbour_reuses": dict(cache.reuses) if cache else {}, "finite": bool(torch.isfinite(xs).all())}
    if device.type == "cuda":
        row["peak_memory_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
    return row, xs


def accuracy(xs: torch.Tensor, reference: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    """Position MSE [m^2] of a rollout x (frames, N, 3) against the fp32 reference rollout and the stored frames."""
    mse_ref = float((xs.float() - reference).square().mean())
    mse_truth = float((xs.float() - truth).square().mean())
    mse_truth_ref = float((reference - truth).square().mean())
    return {"position_mse_vs_fp32_reference_m2": mse_ref, "position_mse_vs_stored_m2": mse_truth,
            "position_mse_relative_difference": abs(mse_truth - mse_truth_ref) / max(mse_truth_ref, 1e-30)}


@torch.no_grad()
def time_projection(model: WorldContact, layout: Any, x: torch.Tensor, cfg: TrainConfig, repeats: int,
                    device: torch.device) -> dict[str, float]:
    """Median ms of one topology projection P (the train config's iterations) of x (B, N, 3): eager (the
    differentiable reference) and as called in rollouts (a replayed CUDA graph on CUDA), and their largest
    absolute difference [m]."""
    proj = model.projection(layout, cfg.smoothing_iterations, cfg.smoothing_weight, cfg.constraint_iterations,
                            cfg.edge_ratio)
    pred = x + 1e-3 * torch.randn_like(x)

    def median_ms(fn: Any) -> float:
        fn(x, pred)
        walls = []
        for _ in range(repeats):
            sync(device)
            t = time.perf_counter()
            fn(x, pred)
            sync(device)
            walls.append(time.perf_counter() - t)
        return 1e3 * statistics.median(walls)

    out = {"ms": median_ms(proj), "eager_ms": median_ms(proj.project),
           "max_abs_difference_m": float((proj(x, pred) - proj.project(x, pred)).abs().max())}
    return out


def _newton_reference(report: dict[str, Any], path: str | None) -> None:
    """Fill report['newton_for_ratios'] from this run's Newton rows, else from a sim_speed report file."""
    rows = {r.get("worlds"): r for r in report["newton"] if "simulated_s_per_wall_s" in r}
    single = rows.get(1)
    multi = max((r for w, r in rows.items() if w and w > 1), key=lambda r: r["worlds"], default=None)
    ref: dict[str, Any] = {"source": "this run"}
    if (single is None or multi is None) and path:
        stored = json.loads(Path(path).read_text())
        n = report["vertices"]
        closest = min({s["bag_vertices"] for s in stored["settings"]}, key=lambda v: abs(v - n))
        settings = [s for s in stored["settings"] if s["bag_vertices"] == closest]
        if single is None:
            single = next((s for s in settings if s["worlds"] == 1), None)
        if multi is None:
            multi = max((s for s in settings if s["worlds"] > 1), key=lambda s: s["worlds"], default=None)
        ref["source"] = f"{path} (an earlier run, not this process)"
    if single is not None:
        ref.update(single_s_per_s=single["simulated_s_per_wall_s"], single_vertices=single["bag_vertices"])
    if multi is not None:
        ref.update(multi_aggregate_s_per_s=multi["simulated_s_per_wall_s_aggregate"], multi_worlds=multi["worlds"],
                   multi_vertices=multi["bag_vertices"])
    report["newton_for_ratios"] = ref




class Report:
    """The report dict, written (JSON + Markdown, atomically) after every row, and the wall-time budget."""

    def __init__(self, out: Path, data: dict[str, Any], budget_s: float, newton_reference: str | None) -> None:
        self.out, self.data, self.budget_s, self.newton_reference = out, data, budget_s, newton_reference
        self.started = time.perf_counter()

    def over_budget(self) -> bool:
        return time.perf_counter() - self.started > self.budget_s

    def write(self) -> None:
        self.data["elapsed_s"] = time.perf_counter() - self.started
        _newton_reference(self.data, self.newton_reference)
        self.data["targets"] = targets_met(self.data)
        write_json_atomic(self.out, self.data)
        md = self.out.with_suffix(".md")
        tmp = md.with_name(f".{md.name}.tmp-{os.getpid()}")
        tmp.write_text(markdown(self.data))
        os.replace(tmp, md)

    def row(self, section: list[dict[str, Any]] | dict[str, Any], key: str | None, label: dict[str, Any],
            fn: Any) -> Any:
        """Run fn() -> (row dict, extra) unless over budget; OOM and errors become the row; write the report."""
        result = None
        if self.over_budget():
            row: dict[str, Any] = {**label, "error": f"skipped: over the {self.budget_s:.0f} s budget"}
        else:
            try:
                row, result = fn()
                row = {**label, **row}
            except torch.OutOfMemoryError as err:  # a finding, not a crash
                row = {**label, "error": f"out of GPU memory: {str(err)[:160]}"}
                torch.cuda.empty_cache()
            except Exception as err:  # noqa: BLE001 - one failing row must not lose the others
                row = {**label, "error": f"{type(err).__name__}: {str(err)[:300]}"}
        if isinstance(section, list):
            section.append(row)
        else:
            section[key] = row
        print(json.dumps({k: v for k, v in row.items() if k != "wall_s"}, default=str), flush=True)
        self.write()
        return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--tag", default="cpu", help="reports/rollout_speed_<tag>.json")
    parser.add_argument("--out-dir", default="reports")
    parser.add_argument("--device", default=None, help="default: the train section's device")
    parser.add_argument("--store", default=None, help="trajectory store whose first episode is rolled out")
    parser.add_argument("--episode", default=None, help="episode id (default: the first lift_handle episode, else the "
                        "first)")
    parser.add_argument("--synthetic", default="carry", help="episode kind of the synthetic store (no --store)")
    parser.add_argument("--checkpoint", default=None, help="trained weights (.safetensors); default random weights")
    parser.add_argument("--frames", type=int, default=20, help="rollout frames per timed rollout")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--batches", type=_ints, default=[8, 32])
    parser.add_argument("--skins", type=_floats, default=None,
                        help="neighbour skins [m] (default: model.neighbor_skin_m and its half and double)")
    parser.add_argument("--train-window", type=int, default=5, help="0: no training row")
    parser.add_argument("--train-steps", type=int, default=5)
    parser.add_argument("--profile-frames", type=int, default=8, help="0: no profile row")
    parser.add_argument("--skip-newton", action="store_true")
    parser.add_argument("--newton-worlds", type=_ints, default=[1, 8], help="world counts of the Newton rows")
    parser.add_argument("--newton-frames", type=int, default=10)
    parser.add_argument("--newton-reference", default=None, help="sim_speed report for ratios without Newton rows")
    parser.add_argument("--budget-s", type=float, default=540.0, help="start no row after this many seconds")
    args = parser.parse_args(argv)

    params = read_params(args.params, args.overrides)
    model_cfg, train_cfg = load_section(params, "model", ModelConfig), load_section(params, "train", TrainConfig)
    device = torch.device(args.device or train_cfg.device)
    skins = args.skins if args.skins is not None else (
        [model_cfg.neighbor_skin_m / 2, model_cfg.neighbor_skin_m, 2 * model_cfg.neighbor_skin_m]
        if model_cfg.neighbor_skin_m > 0 else [0.25 * model_cfg.spatial_radius_m])
    out = Path(args.out_dir) / f"rollout_speed_{args.tag}.json"
    with tempfile.TemporaryDirectory() as tmp:
        store_path = Path(args.store) if args.store else None
        if store_path is None:
            from tests.synthetic_store import write_synthetic_store  # noqa: PLC0415 - only without --store

            store_path = write_synthetic_store(Path(tmp) / "synthetic.zarr", params, [(args.synthetic, "test")],
                                               frames=args.frames + 2)
        store = TrajectoryStore(store_path)
        episode = args.episode or next((e for e in store.episode_ids if store.episode_attrs(e).get("task") == TASK),
                                       store.episode_ids[0])
        phase, model, layout = episode_model(store, model_cfg, device, episode)
        if args.checkpoint:
            model = load_model(args.checkpoint, device)[0]
        model.eval()
        frames = min(args.frames, phase.stop - phase.start - 1)
        a = {k: torch.from_numpy(v).to(device) for k, v in read_phase_window(store, phase, 0, frames + 1).items()}
        data: dict[str, Any] = {
            "benchmark": "rollout_speed", "command": " ".join(sys.argv), "params": args.params,
            "overrides": args.overrides, "environment": environment_info(str(device)),
            "episode": f"{store_path if args.store else 'synthetic ' + args.synthetic} / {episode}",
            "weights": args.checkpoint or "random", "vertices": layout.num_vertices,
            "samples": int(layout.sample_points.shape[0]), "dt": store.dt, "frames": frames,
            "radii_m": {k: getattr(model.config, k) for k in ("spatial_radius_m", "controllable_radius_m",
                                                               "environment_radius_m", "topology_radius_m")},
            "single": [], "batched": [], "newton": [], "other": {},
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        rep = Report(out, data, args.budget_s, args.newton_reference)
        truth = a["x"][1:frames + 1]
        cuda = device.type == "cuda"
        variants = [("fp32 reference", False, 0.0)] + ([("bf16", True, 0.0)] if cuda else [])
        variants += [(f"{'bf16' if cuda else 'fp32'} + neighbour reuse, skin {s * 1e3:g} mm", cuda, s) for s in skins]
        reference = None
        for name, bf16, skin in variants:
            def single(bf16: bool = bf16, skin: float = skin) -> tuple[dict[str, Any], torch.Tensor]:
                row, xs = time_variant(model, layout, a, store.dt, frames, 1, bf16, skin, args.repeats, device)
                return {**row, **(accuracy(xs[0], reference, truth) if reference is not None else {})}, xs[0].float()
            xs = rep.row(data["single"], None, {"variant": name}, single)
            if reference is None and xs is not None:
                reference = xs
                data["single"][-1].update(accuracy(xs, xs, truth))
        timed = [r for r in data["single"] if "ms_per_step_median" in r]
        fastest = min(timed, key=lambda r: r["ms_per_step_median"]) if timed else {"bf16": cuda, "skin_m": 0.0,
                                                                                      "variant": "none"}
        projection = model.projection(layout, train_cfg.smoothing_iterations, train_cfg.smoothing_weight,
                                      train_cfg.constraint_iterations, train_cfg.edge_ratio)
        rep.row(data["single"], None, {"variant": f"{fastest['variant']} + topology projection P"},
                lambda: time_variant(model, layout, a, store.dt, frames, 1, fastest["bf16"], fastest["skin_m"],
                                     args.repeats, device, projection))
        for batch in args.batches:
            for skin in dict.fromkeys([0.0, fastest["skin_m"]]):
                name = f"{'bf16' if fastest['bf16'] else 'fp32'}" + (f" + reuse, skin {skin * 1e3:g} mm" if skin else "")
                rep.row(data["batched"], None, {"variant": name, "batch": batch},
                        lambda b=batch, s=skin: time_variant(model, layout, a, store.dt, frames, b, fastest["bf16"],
                                                             s, args.repeats, device))
        if args.profile_frames > 0:
            cfg = replace(model.config, neighbor_skin_m=fastest["skin_m"])
            rep.row(data["other"], "profile", {"variant": fastest["variant"]},
                    lambda: (profile(store, cfg, args.profile_frames, 1, fastest["bf16"], device), None))
        rep.row(data["other"], "projection", {"constraint_iterations": train_cfg.constraint_iterations},
                lambda: (time_projection(model, layout, a["x"][:1], train_cfg, args.repeats, device), None))
        if "ms" in data["other"]["projection"]:
            data["other"]["projection_ms"] = data["other"]["projection"]["ms"]
            if timed:
                data["other"]["projection_share_of_fastest_step"] = (data["other"]["projection_ms"]
                                                                     / fastest["ms_per_step_median"])
        if args.train_window > 0:
            rep.row(data["other"], "training", {"window": args.train_window},
                    lambda: (time_training(store, model_cfg, train_cfg, args.train_window, args.train_steps, device),
                             None))
        if not args.skip_newton:
            for worlds in args.newton_worlds:
                overrides = [*args.overrides, f"sim.worlds={worlds}", f"sim.device={device}"]
                rep.row(data["newton"], None, {"worlds": worlds},
                        lambda o=overrides: (measure(read_params(args.params, o), args.newton_frames, 1), None))
        rep.write()
    print(markdown(rep.data), flush=True)


if __name__ == "__main__":
    main()
