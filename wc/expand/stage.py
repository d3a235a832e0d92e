"""Stage `expand`: more trajectories of one task from the world model (data/expanded/trajectories.zarr,
reports/expand.json).

Each generated episode starts from a source episode's settled frame 0 (parents of the proposed cell taken in
turn, else all of them), moved rigidly on the table (wc.expand.transform); the coverage planner proposes its
cell, speed and amplitude, the task program plans the right arm's actions against the moved state
(wc.expand.plan; a plan whose frame 0 already penetrates the start posture is infeasible), and WorldContact
rolls the batch out autoregressively from v = 0 under the prescribed link and table poses (wc.expand.batched_rollout),
with a projection after every step (`projection`: edges and contacts together, wc.expand.constraints, or the
contact push alone, wc.expand.contact). Every
rollout then faces the source data's checks (wc.validate.predicates, in their order, plus the task's own
verdict when `task_check`); only the episodes that pass are written, the others are counted by their first
failing check. Generation stops when the task's source episodes plus the accepted generated ones reach
`target_trajectories`, or after `max_attempts` planned episodes; the report says whether the target was met.
"""

from __future__ import annotations

import json
import time
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from wc.agent.planner import CoveragePlanner
from wc.config import load_section, params_hash
from wc.data.store import TrajectoryStore, TrajectoryWriter
from wc.devices import resolve_device, resolve_warp_device
from wc.eval.predictors import CHECKPOINT, WorldContactPredictor
from wc.expand.carry import PadCarry
from wc.expand.config import ExpandConfig
from wc.expand.constraints import JointStepProjection
from wc.expand.contact import ContactProjectedPredictor
from wc.expand.crossing_free import CrossingFreeStep
from wc.expand.plan import PlannedEpisode, SourceEpisode, pick_parent, plan_episode, source_episodes
from wc.expand.batched_rollout import Rollout, rollout_batch
from wc.expand.self_contact import SelfContactSeparation
from wc.expand.untangle import SelfIntersectionGuard
from wc.model.layout import scene_layout
from wc.paths import EXPAND
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.scene.scene import Scene
from wc.sim.config import SimConfig
from wc.seeds import SeedStream, episode_seed
from wc.tasks.base import UNREACHABLE, InfeasibleEpisode, Task, get_task
from wc.train.config import TrainConfig
from wc.validate.config import ValidateConfig
from wc.validate.predicates import PREDICATES, Episode, blow_up_detail, first_failure
from wc.validate.stage import EpisodeScenes

SECTIONS = ["expand", "scene", "tasks", "validate", "train", "sim"]


def verdict(task: Task, scene: Scene, task_check: bool, planned: PlannedEpisode, r: Rollout,
            cfg: ValidateConfig, frame_dt_s: float) -> tuple[str, int] | None:
    """(first failing check, frame) of a generated episode: the source data's predicates, then (if asked) the
    task's own verdict on the last frame; None when it passes."""
    failure = first_failure(scene, r.x, r.v, r.action, r.link_poses, cfg, frame_dt_s=frame_dt_s)
    if failure is not None or not task_check:
        return failure
    reason = task.check(scene, planned.spec, r.x, r.action)
    return (reason, len(r.x) - 1) if reason else None


def _failure_detail(scene: Scene, r: Rollout, cfg: ValidateConfig, dt: float, reason: str,
                    frame: int) -> dict[str, Any]:
    """A blow_up's sub-criterion (speed or strain) and both values at its frame; nothing for other reasons."""
    if reason != "blow_up":
        return {}
    return blow_up_detail(scene, Episode(r.x, r.v, r.action, r.link_poses, dt), cfg, frame)


def joint_projection(cfg: ExpandConfig, scene: Scene, sim: SimConfig, validate_cfg: ValidateConfig
                     ) -> JointStepProjection | None:
    """The per-step projection `expand.projection: joint` asks for, with its options; None for the others."""
    if cfg.projection != "joint":
        return None
    carry = PadCarry(scene, cfg.pad_carry_radius_m) if cfg.pad_carry else None
    def rollback() -> SelfIntersectionGuard:
        return SelfIntersectionGuard(scene, cfg.untangle_rounds, resolve_warp_device(validate_cfg.device, "validate.device"))

    untangle = {"none": lambda: None, "rollback": rollback,
                "bounded": lambda: CrossingFreeStep(scene, cfg.untangle_share, cfg.untangle_rounds),
                "bounded+rollback": lambda: CrossingFreeStep(scene, cfg.untangle_share, cfg.untangle_rounds, hold=False,
                                                             then=rollback())}[cfg.untangle]()
    self_contact = (SelfContactSeparation(scene, sim.self_contact_gap_m, sim.self_contact_filter_rings)
                    if cfg.self_contact else None)
    return JointStepProjection(scene, cfg.projection_edge_ratio, cfg.projection_iterations, carry,
                               untangle, self_contact, cfg.projection_final_edge_passes)


def _untangle_stats(projection: JointStepProjection | None) -> dict[str, Any] | None:
    """The self-crossing guard's counters (and its follow-up guard's, under "then"); None without a guard."""
    guard = projection.untangle if projection is not None else None
    if guard is None:
        return None
    then = getattr(guard, "then", None)
    return {**guard.stats, **({"then": then.stats} if then is not None else {})}


def _checkpoint_info(model_dir: Path) -> dict[str, Any]:
    config = json.loads(model_dir.joinpath(CHECKPOINT).with_suffix(".json").read_text())
    return {"path": str(model_dir), **{k: config.get(k) for k in ("params_hash", "step", "stage", "projection", "dt")}}


def _copy_scene(src: TrajectoryStore, writer: TrajectoryWriter) -> None:
    for o in src.objects.values():
        writer.add_object(o.name, o.rest_positions, o.faces, o.rest_uv, o.vertex_area, o.kind, o.tag, o.material)
    for p in src.prescribed.values():
        writer.add_prescribed(p.name, p.local_points, p.local_normals, p.tag, p.link)


def _episode_attrs(planned: PlannedEpisode, source: SourceEpisode, failure: str | None = None) -> dict[str, Any]:
    s = planned.spec
    return {"task": s.task, "seed": s.seed, "cell": s.cell, "speed": s.speed, "amplitude": s.amplitude,
            "split": "train", "accepted": failure is None, "first_failure": failure, "source": "worldcontact",
            "parent": planned.parent, "yaw_deg": planned.yaw_deg, "shift_m": list(planned.shift_m), **source.layout}


def expand(params: dict[str, Any], model_dir: str | Path = EXPAND["model"], store: str | Path = EXPAND["store"],
           out: str | Path = EXPAND["out"], report: str | Path = EXPAND["report"],
           rejected_out: str | Path | None = None) -> dict[str, Any]:
    """Generate and check episodes until the target is met or the attempts run out; write the accepted ones
    to `out` and the rejected ones (accepted false, first_failure their check) to `rejected_out` (None: not
    kept), each atomically and possibly empty, and the report to `report`. Returns the report. The rejected
    store is what lets the teacher check measure recall as well as precision."""
    cfg = load_section(params, "expand", ExpandConfig)
    scene_cfg = load_section(params, "scene", SceneConfig)
    validate_cfg = load_section(params, "validate", ValidateConfig)
    train_cfg = load_section(params, "train", TrainConfig)
    store, out, model_dir = Path(store), Path(out), Path(model_dir)
    rejected_out = Path(rejected_out) if rejected_out is not None else None
    if not store.exists():
        raise FileNotFoundError(f"source trajectory store {store} not found: run the validate stage first "
                                "(`dvc repro validate`)")
    if not (model_dir / CHECKPOINT).is_file():
        raise FileNotFoundError(f"world model checkpoint {model_dir / CHECKPOINT} not found: run the train stage "
                                "first (`dvc repro train`)")
    if out.resolve() == store.resolve() or (rejected_out is not None and rejected_out.resolve() in (store.resolve(),
                                                                                                   out.resolve())):
        raise ValueError(f"expand would overwrite a store: its outputs {out} and {rejected_out} must differ from "
                         f"each other and from its input {store}")
    started = time.perf_counter()
    task = get_task(cfg.task, params)
    src = TrajectoryStore(store)
    sources, scene = source_episodes(src, task, EpisodeScenes(scene_cfg, src))
    device = resolve_device(cfg.device, "expand.device")
    torch.manual_seed(cfg.seed)
    model = WorldContactPredictor.from_dir(model_dir, train_cfg, device)
    layout = scene_layout(src, list(scene.objects), list(scene.link_names), model.tag_scale).to(device)
    projection = joint_projection(cfg, scene, load_section(params, "sim", SimConfig), validate_cfg)
    predictor = model if cfg.projection == "none" else ContactProjectedPredictor(model, scene, projection)
    dt = src.dt
    checkpoint = _checkpoint_info(model_dir)
    if checkpoint["dt"] is not None and abs(float(checkpoint["dt"]) - dt) > 1e-9:
        raise ValueError(f"{model_dir}: the model was trained at frame dt {checkpoint['dt']} s, {store} has {dt} s")
    phash = params_hash(params, SECTIONS)

    planner = CoveragePlanner()  # this run's outcomes only: the simulator's memory is about another dynamics
    wanted = max(0, cfg.target_trajectories - len(sources))
    rejections: dict[str, int] = {name: 0 for name in PREDICATES}
    rejected: list[dict[str, Any]] = []
    infeasible: list[dict[str, Any]] = []
    attempts = generated = accepted = frames = 0
    rollout_s = 0.0
    def writer_to(path: Path | None) -> TrajectoryWriter | nullcontext[None]:
        if path is None:
            return nullcontext()
        return TrajectoryWriter(path, dt=dt, substeps=int(src.attrs["substeps"]), units=src.attrs["units"],
                                params_hash=phash, created_by="stages.expand", object_order=src.object_names,
                                link_names=src.link_names, env_names=src.env_names,
                                chunk_frames=src.chunk_frames(sources[0].eid))

    with writer_to(out) as writer, writer_to(rejected_out) as rejected_writer, \
            tqdm(total=wanted, desc=f"expand {task.name}", unit="trajectory") as bar:
        for w in (writer, rejected_writer):
            if w is not None:
                _copy_scene(src, w)
        while accepted < wanted and attempts < cfg.max_attempts and not (
                cfg.max_minutes > 0 and time.perf_counter() - started > 60.0 * cfg.max_minutes):
            planned: list[tuple[PlannedEpisode, SourceEpisode]] = []
            for i in range(attempts, attempts + min(cfg.batch_size, wanted - accepted, cfg.max_attempts - attempts)):
                spec = planner.propose(task, episode_seed(cfg.seed, 0, i, SeedStream.EXPAND))
                source = pick_parent(sources, spec.cell, i)
                try:
                    planned.append((plan_episode(task, scene, source, spec, cfg, dt, validate_cfg), source))
                except InfeasibleEpisode as err:
                    planner.record(spec, UNREACHABLE)
                    infeasible.append({"seed": spec.seed, "cell": spec.cell, "parent": source.eid, "reason": str(err)})
                attempts += 1
            if not planned:
                continue
            t0 = time.perf_counter()
            rollouts = rollout_batch(predictor, layout, scene, [p for p, _ in planned], dt, device)
            rollout_s += time.perf_counter() - t0
            for (p, source), r in zip(planned, rollouts):
                failure = verdict(task, scene, cfg.task_check, p, r, validate_cfg, dt)
                planner.record(p.spec, *(failure or (None, None)))
                generated += 1
                frames += len(r.x)
                if failure is not None:
                    rejections[failure[0]] = rejections.get(failure[0], 0) + 1
                    rejected.append({"seed": p.spec.seed, "cell": p.spec.cell, "parent": p.parent,
                                     "reason": failure[0], "frame": failure[1], "frames": len(r.x),
                                     **_failure_detail(scene, r, validate_cfg, dt, *failure)})
                    if rejected_writer is not None:
                        rejected_writer.add_episode(r.x, r.v, r.action, r.link_poses, r.env_poses,
                                                    **_episode_attrs(p, source, failure[0]))
                    continue
                writer.add_episode(r.x, r.v, r.action, r.link_poses, r.env_poses, **_episode_attrs(p, source))
                accepted += 1
                bar.update(1)
            bar.set_postfix(generated=generated, rejected=generated - accepted)
    wall = time.perf_counter() - started
    result = {
        "task": task.name,
        "source_episodes": len(sources),
        "sources": [{"episode": s.eid, "cell": s.cell, "presettle_state": s.presettle} for s in sources],
        "projection": cfg.projection,
        "pad_carry": cfg.pad_carry,
        "projection_stats": projection.stats if projection is not None else None,
        "untangle": cfg.untangle,
        "self_contact": cfg.self_contact,
        "untangle_stats": _untangle_stats(projection),
        "target_trajectories": cfg.target_trajectories,
        "wanted_generated": wanted,
        "attempts": attempts,
        "infeasible_plans": len(infeasible),
        "generated": generated,
        "accepted": accepted,
        "rejected": generated - accepted,
        "rejections": rejections,
        "acceptance_rate": accepted / generated if generated else None,
        "expanded_total": len(sources) + accepted,
        "target_reached": len(sources) + accepted >= cfg.target_trajectories,
        "frames_generated": frames,
        "rollout_s": rollout_s,
        "model_frames_per_s": frames / rollout_s if rollout_s else None,
        "wall_s": wall,
        "stopped_early": accepted < wanted and attempts < cfg.max_attempts,
        "trajectories_per_min": 60.0 * generated / wall,
        "accepted_per_min": 60.0 * accepted / wall,
        "coverage": planner.coverage(task),
        "rejected_episodes": rejected,
        "infeasible": infeasible,
        "device": str(device),
        "model": checkpoint,
        "store": str(store),
        "out": str(out),
        "rejected_out": str(rejected_out) if rejected_out is not None else None,
        "params_hash": phash,
        "environment": environment_info(str(device)),
    }
    write_json_atomic(report, result)
    return result


def expand_summary(r: dict[str, Any]) -> str:
    """The line `python -m stages.expand` prints."""
    failed = ", ".join(f"{k} {v}" for k, v in r["rejections"].items() if v) or "none"
    return (f"expand {r['task']}: {r['accepted']}/{r['generated']} generated episodes accepted "
            f"({r['infeasible_plans']} plans infeasible); rejected: {failed}; {r['expanded_total']}/"
            f"{r['target_trajectories']} trajectories with the {r['source_episodes']} source ones"
            f"{'' if r['target_reached'] else ' (target NOT reached)'}; {r['trajectories_per_min']:.2f} generated/min "
            f"on {r['device']}, {r['wall_s']:.1f} s")
