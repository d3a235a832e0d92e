"""The slot engine's frame on a device: captured as CUDA graphs (and compiled, with expand.slots.compile_*) against
run eagerly and uncompiled (the same trajectories), and its cost per frame against the number of slots.

    python -m benchmarks.expand_smoke [--params params.yaml] [--set key=value ...] [--device cuda]
        [--model models/pretrained/worldcontact-lift-handle] [--slots 4,64,128,256] [--frames 40] --out FILE.json

The shipped model rolls out the params' bag at rest on the table under a scripted reach of the right arm (its frame-0
posture held, then a lift), in every slot; the first slot count also runs eagerly, nothing captured or
compiled, and the largest difference between the two trajectories is reported; every count is timed after a warm-up
(ms per frame, slot-frames per second, the parts of a frame). No Newton, no trajectory store beyond the scene's: a
minute on a bare GPU machine.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch

from wc.agent.runner import simulator_store
from wc.config import add_params_arguments, load_section, read_params
from wc.data.store import TrajectoryStore
from wc.expand.config import ExpandConfig
from wc.expand.plan import SourceEpisode
from wc.expand.slot_rollout import SlotPlan
from wc.expand.slot_stage import SlotModel
from wc.model.prescribed_inputs import KinematicInputs
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.sim.config import SimConfig
from wc.tasks.base import get_task
from wc.validate.config import ValidateConfig


def scripted_plan(scene: Any, frames: int) -> SlotPlan:
    """The bag at rest on the table and the arms at home, the right gripper opening then rising 5 cm (a plan needs no
    planner here: only the frame's cost and its graph against eager matter)."""
    x0 = np.concatenate([m.vertices for m in scene.objects.values()]).astype(np.float32) + [0.0, 0.0, 1e-3]
    actions = np.repeat(scene.home_action()[None], frames, axis=0).astype(np.float32)
    actions[:, 13] = np.linspace(0.0, 0.04, frames)  # the right gripper opens
    actions[:, 8] += np.linspace(0.0, 0.3, frames)  # and its shoulder lifts
    return SlotPlan(x0, KinematicInputs(scene).poses(actions[None])[0])


def _timed(rollout: Any, plan: SlotPlan, frames: int) -> tuple[float, np.ndarray]:
    slots = list(range(rollout.batch))
    rollout.load(slots, [plan] * rollout.batch)
    rollout.capture()
    rollout.load(slots, [plan] * rollout.batch)
    rollout.advance(2)
    rollout.read_failures()
    rollout.part_s = dict.fromkeys(rollout.part_s, 0.0)
    rollout.load(slots, [plan] * rollout.batch)
    started = time.perf_counter()
    rollout.advance(frames - 1)
    rollout.read_failures()
    wall = time.perf_counter() - started
    return wall, rollout.take([0], [frames - 1])[0][0]


@contextmanager
def slot_models(params: dict[str, Any], model_dir: str, frames: int) -> Iterator[tuple[SlotPlan, Any]]:
    """(the scripted plan, make(slots) -> SlotModel): the params' task scene, its store (scene only, in a temporary
    folder) and the shipped model for any number of slots."""
    scene_cfg, sim_cfg = load_section(params, "scene", SceneConfig), load_section(params, "sim", SimConfig)
    task = get_task(load_section(params, "expand", ExpandConfig).task, params)
    scene = build_scene(scene_cfg, task.objects, held=task.held())
    plan = scripted_plan(scene, frames)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scene.zarr"
        with simulator_store(path, scene_cfg, sim_cfg, [task], "smoke", "benchmarks.expand_smoke"):
            pass
        store = TrajectoryStore(path)
        source = SourceEpisode("none", 0, plan.x0, {}, plan.x0)

        def make(slots: int, **slot_keys: Any) -> SlotModel:
            expand_params = {**params["expand"], "batch_size": slots,
                             "slots": {**params["expand"].get("slots", {}), **slot_keys}}
            return SlotModel({**params, "expand": expand_params}, Path(model_dir), scene, store, [source],
                             load_section({"expand": expand_params}, "expand", ExpandConfig),
                             load_section(params, "validate", ValidateConfig))

        yield plan, make


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--model", default="models/pretrained/worldcontact-lift-handle")
    parser.add_argument("--slots", default="4,64,128,256")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--out", default="reports/expand_smoke.json")
    args = parser.parse_args(argv)
    params = read_params(args.params, [*args.overrides, f"expand.device={args.device}"])
    rows: list[dict[str, Any]] = []
    with slot_models(params, args.model, args.frames) as (plan, make):
        for k, slots in enumerate(int(s) for s in args.slots.split(",")):
            model = make(slots)
            graphed = model.rollout(args.frames)
            wall, x_graph = _timed(graphed, plan, args.frames)
            row = {"slots": slots, "ms_per_frame": 1e3 * wall / (args.frames - 1),
                   "slot_frames_per_s": slots * (args.frames - 1) / wall, "graphs": graphed.use_graphs,
                   "parts_s": dict(graphed.part_s), "finite": bool(np.isfinite(x_graph).all())}
            if k == 0:  # the reference: every part run eagerly, nothing compiled
                eager = make(slots, cuda_graph=False, compile_network=False, compile_projection=False)
                _, x_eager = _timed(eager.rollout(args.frames), plan, args.frames)
                row["max_graph_vs_eager_m"] = float(np.nanmax(np.abs(x_graph - x_eager)))
                row["compiled"] = {key: getattr(model.cfg.slots, key)
                                   for key in ("compile_network", "compile_projection")}
                del eager
            rows.append(row)
            print(row, flush=True)
            write_json_atomic(args.out, {"benchmark": "expand_smoke", "device": args.device, "frames": args.frames,
                                         "environment": environment_info(args.device), "rows": rows})
            del model, graphed
            torch.cuda.empty_cache() if args.device.startswith("cuda") else None


if __name__ == "__main__":
    main()
