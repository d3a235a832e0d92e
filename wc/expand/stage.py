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

Two engines (`engine`), the same checks and stores:
- `slots` (default): `batch_size` slots on the device, each rolling out its own episode and taking the next plan when
  it ends or fails; the projection with fixed pass counts and the one-frame checks on the device, captured as CUDA
  graphs; planning in worker processes beside the rollouts (wc.expand.slot_stage, slot_expansion, slot_rollout).
- `batches`: the reference; a batch's rollouts and checks are a work unit (wc.expand.worker), run in this process
  or, with `executor: ray`, as Ray tasks; the planning and the writing stay here, and the verdicts are filed in
  planning order (`ExpandPlans`, wc.distributed.streams), so either executor writes the same episodes.
Either way the verdicts are filed, and episodes written, in proposal order: the same params give the same stores.
With `shards` > 1 the expansion is split into that many independent shares run on the devices of this host and
concatenated in shard order (wc.expand.shards).
"""

from __future__ import annotations

import json
import secrets
import time
from collections import deque
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path
from typing import Any

from tqdm import tqdm

from wc.agent.planner import CoveragePlanner
from wc.config import load_section, params_hash, without_keys
from wc.data.store import TrajectoryStore, TrajectoryWriter, copy_scene
from wc.distributed import UnitsFailed, Unit, WorkerSpec, drive, every_unit, open_executor, uses_cuda
from wc.model.predictor import CHECKPOINT
from wc.model_ref import model_record, resolve_model_dir
from wc.expand.config import ExpandConfig
from wc.expand.generated_store import episode_attrs
from wc.expand.plan_pool import PlanPool
from wc.expand.slot_expansion import SlotExpansion
from wc.expand.slot_stage import SlotModel, run_slots
from wc.expand.plan import PlannedEpisode, SourceEpisode, pick_parent, plan_episode, plan_seed, source_episodes
from wc.expand.shards import expand_in_shards, share
from wc.expand.worker import Counters, ExpandBatch, ExpandWorker, load_expand_worker, merged_counters
from wc.paths import EXPAND
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.scene.scene import Scene
from wc.tasks.base import UNREACHABLE, InfeasibleEpisode, Task, get_task
from wc.validate.config import ValidateConfig
from wc.validate.predicates import PREDICATES
from wc.scene.episode_scenes import EpisodeScenes

SECTIONS = ["expand", "scene", "tasks", "validate", "train", "sim"]


def _checkpoint_info(model_ref: str | Path, model_dir: Path) -> dict[str, Any]:
    """The report's record of the model: the reference as given, its weights' SHA-256, params hash, step, stage,
    projection and frame dt."""
    config = json.loads(model_dir.joinpath(CHECKPOINT).with_suffix(".json").read_text())
    return {**model_record(model_ref, model_dir / CHECKPOINT), **{k: config.get(k) for k in ("projection", "dt")}}


class ExpandPlans:
    """The planner's side of the expansion, a stream of batches (wc.distributed.streams): each batch is planned from
    every verdict filed before it; its verdicts are filed, and its episodes written, in planning order. Stops
    planning once the accepted episodes plus those in flight reach `wanted`, after `max_attempts`, or after
    `max_minutes` from `started` (time.perf_counter()); `shard`: whose plan seeds (wc.expand.plan.plan_seed)."""

    def __init__(self, task: Task, scene: Scene, sources: list[SourceEpisode], cfg: ExpandConfig,
                 validate_cfg: ValidateConfig, dt: float, wanted: int, worker: WorkerSpec, started: float,
                 model_sha256: str | None = None, shard: int = 0) -> None:
        self.task, self.scene, self.sources, self.cfg, self.validate_cfg = task, scene, sources, cfg, validate_cfg
        self.shard = shard
        self.dt, self.wanted, self.worker, self.started = dt, wanted, worker, started
        self.model_sha256 = model_sha256  # recorded in every generated episode's attrs (the teacher check reports it)
        self.planner = CoveragePlanner()  # this run's outcomes only: the simulator's memory is about another dynamics
        self.attempts = self.generated = self.accepted = self.frames = self.in_flight = 0
        self.rollout_s = 0.0
        self.rejections: dict[str, int] = {name: 0 for name in PREDICATES}
        self.rejected: list[dict[str, Any]] = []
        self.infeasible: list[dict[str, Any]] = []
        self.counters: Counters = {}
        self.device: str | None = None  # where the batches ran
        self.environment: dict[str, str] | None = None
        self._batches: deque[list[tuple[PlannedEpisode, SourceEpisode]]] = deque()
        self.writer: TrajectoryWriter | None = None
        self.rejected_writer: TrajectoryWriter | None = None
        self.bar: tqdm | None = None

    def _may_plan(self) -> bool:
        cfg = self.cfg
        return (self.accepted + self.in_flight < self.wanted and self.attempts < cfg.max_attempts
                and not (cfg.max_minutes > 0 and time.perf_counter() - self.started > 60.0 * cfg.max_minutes))

    def next_unit(self) -> Unit | None:
        cfg = self.cfg
        while self._may_plan():
            planned: list[tuple[PlannedEpisode, SourceEpisode]] = []
            first = self.attempts
            for i in range(first, first + min(cfg.batch_size, self.wanted - self.accepted - self.in_flight,
                                              cfg.max_attempts - first)):
                spec = self.planner.propose(self.task, plan_seed(cfg.seed, self.shard, i))
                source = pick_parent(self.sources, spec.cell, i)
                try:
                    planned.append((plan_episode(self.task, self.scene, source, spec, cfg, self.dt, self.validate_cfg),
                                    source))
                except InfeasibleEpisode as err:
                    self.planner.record(spec, UNREACHABLE)
                    self.infeasible.append({"seed": spec.seed, "cell": spec.cell, "parent": source.eid,
                                            "reason": str(err)})
                self.attempts += 1
            if planned:
                self._batches.append(planned)
                self.in_flight += len(planned)
                return Unit(self.worker, [p for p, _ in planned], f"expand plans {first}-{self.attempts - 1}")
        return None

    def file(self, batch: ExpandBatch) -> None:
        planned = self._batches.popleft()
        self.in_flight -= len(planned)
        self.rollout_s += batch.rollout_s
        self.counters = merged_counters(self.counters, batch.counters)
        self.device, self.environment = batch.device, batch.environment
        for (p, source), r, failure, detail in zip(planned, batch.rollouts, batch.failures, batch.details):
            self.planner.record(p.spec, *(failure or (None, None)))
            self.generated += 1
            self.frames += len(r.x)
            if failure is not None:
                self.rejections[failure[0]] = self.rejections.get(failure[0], 0) + 1
                self.rejected.append({"seed": p.spec.seed, "cell": p.spec.cell, "parent": p.parent,
                                      "reason": failure[0], "frame": failure[1], "frames": len(r.x), **detail})
                if self.rejected_writer is not None:
                    self.rejected_writer.add_episode(r.x, r.v, r.action, r.link_poses, r.env_poses,
                                                     **episode_attrs(p, source, failure[0], self.model_sha256))
                continue
            self.writer.add_episode(r.x, r.v, r.action, r.link_poses, r.env_poses,
                                    **episode_attrs(p, source, model_sha256=self.model_sha256))
            self.accepted += 1
            self.bar.update(1)
        self.bar.set_postfix(generated=self.generated, rejected=self.generated - self.accepted)


def expand(params: dict[str, Any], model_dir: str | Path = EXPAND["model"], store: str | Path = EXPAND["store"],
           out: str | Path = EXPAND["out"], report: str | Path = EXPAND["report"],
           rejected_out: str | Path | None = None) -> dict[str, Any]:
    """Generate and check episodes until the target is met or the attempts run out; write the accepted ones
    to `out` and the rejected ones (accepted false, first_failure their check) to `rejected_out` (None: not
    kept), each atomically and possibly empty, and the report to `report`. Returns the report. The rejected
    store is what lets the teacher check measure recall as well as precision. Ray units that kept failing: the
    report lists them, neither store is written, UnitsFailed. `expand.shards` > 1: wc.expand.shards."""
    model_ref, store, out = model_dir, Path(store), Path(out)
    rejected_out = Path(rejected_out) if rejected_out is not None else None
    if load_section(params, "expand", ExpandConfig).shards == 1:
        return expand_share(params, model_ref, store, out, report, rejected_out)
    for name, cls in (("scene", SceneConfig), ("validate", ValidateConfig)):  # bad input fails before any output
        load_section(params, name, cls)
    model_dir = _checked_inputs(model_ref, store, out, rejected_out)
    result = expand_in_shards(params, expand_share, model_dir, store, out, rejected_out, _params_hash(params),
                              _checkpoint_info(model_ref, model_dir))
    write_json_atomic(report, result)
    return result


def _params_hash(params: dict[str, Any]) -> str:
    """What the stores depend on (not where the work ran)."""
    return params_hash(without_keys(params, "expand", ("executor",)), SECTIONS)


def _checked_inputs(model_ref: str | Path, store: Path, out: Path, rejected_out: Path | None) -> Path:
    """The local model folder of `model_ref`, once the source store exists and the outputs overwrite no store."""
    if not store.exists():
        raise FileNotFoundError(f"source trajectory store {store} not found: run the validate stage first "
                                "(`dvc repro validate`)")
    try:  # a model folder, or hf://owner/repo[/folder]: downloaded once, every worker reads the local copy
        model_dir = resolve_model_dir(model_ref, "expand --model")
    except FileNotFoundError as err:
        raise FileNotFoundError(f"world model: {err}: run the train stage first (`dvc repro train`)") from err
    if out.resolve() == store.resolve() or (rejected_out is not None and rejected_out.resolve() in (store.resolve(),
                                                                                                   out.resolve())):
        raise ValueError(f"expand would overwrite a store: its outputs {out} and {rejected_out} must differ from "
                         f"each other and from its input {store}")
    return model_dir


def expand_share(params: dict[str, Any], model_ref: str | Path, store: Path, out: Path, report: str | Path,
                 rejected_out: Path | None, shard: int = 0) -> dict[str, Any]:
    """`expand` of shard `shard`'s share of the wanted episodes and attempts (all of them when expand.shards is 1),
    with its plan seeds; the whole expansion in one process (its engine's own planning processes aside)."""
    cfg = load_section(params, "expand", ExpandConfig)
    scene_cfg = load_section(params, "scene", SceneConfig)
    validate_cfg = load_section(params, "validate", ValidateConfig)
    model_dir = _checked_inputs(model_ref, store, out, rejected_out)
    cfg = replace(cfg, max_attempts=share(cfg.max_attempts, cfg.shards, shard))
    started = time.perf_counter()
    task = get_task(cfg.task, params)
    src = TrajectoryStore(store)
    sources, scene = source_episodes(src, task, EpisodeScenes(scene_cfg, src), cfg.max_sources)
    dt = src.dt
    checkpoint = _checkpoint_info(model_ref, model_dir)
    if checkpoint["dt"] is not None and abs(float(checkpoint["dt"]) - dt) > 1e-9:
        raise ValueError(f"{model_dir}: the model was trained at frame dt {checkpoint['dt']} s, {store} has {dt} s")
    phash = _params_hash(params)
    wanted = share(max(0, cfg.target_trajectories - len(sources)), cfg.shards, shard)

    def writer_to(path: Path | None) -> TrajectoryWriter | nullcontext[None]:
        if path is None:
            return nullcontext()
        return TrajectoryWriter(path, dt=dt, substeps=int(src.attrs["substeps"]), units=src.attrs["units"],
                                params_hash=phash, created_by="stages.expand", object_order=src.object_names,
                                link_names=src.link_names, env_names=src.env_names,
                                chunk_frames=src.chunk_frames(sources[0].eid), write_processes=cfg.write_processes)

    if cfg.engine == "slots":
        with PlanPool(params, scene, sources, cfg, dt, validate_cfg, cfg.slots.planner_workers) as pool:  # before CUDA
            model = SlotModel(params, model_dir, scene, src, sources, cfg, validate_cfg)  # loads before any output
            with writer_to(out) as writer, writer_to(rejected_out) as rejected_writer:
                for w in (writer, rejected_writer):
                    if w is not None:
                        copy_scene(src, w)
                slots = run_slots(model, pool, task, scene, sources, wanted, writer, rejected_writer, started,
                                  checkpoint["sha256"], shard)
        result = {**_report(slots, cfg, sources, checkpoint, store, out, rejected_out, phash, {"name": "local"},
                            str(model.device), environment_info(str(model.device)), time.perf_counter() - started),
                  "engine": "slots", "slots": cfg.batch_size, "sync_every": cfg.slots.sync_every,
                  "slot_loads": slots.loads, "restarts": slots.restarts,
                  "tail_shrinks": slots.shrinks, "unused_proposals": slots.unused,
                  "timing": slots.timing()}
        write_json_atomic(report, result)
        return result
    if cfg.executor == "local":  # the model loads before any output, as it always did
        local = ExpandWorker(params, model_dir, scene, src)
        worker = WorkerSpec("expand", lambda: local)
    else:  # each Ray worker process loads the model once for this run
        worker = WorkerSpec(f"expand:{secrets.token_hex(8)}", load_expand_worker,
                            (params, str(model_dir.resolve()), str(store.resolve())))
    plans = ExpandPlans(task, scene, sources, cfg, validate_cfg, dt, wanted, worker, started, checkpoint["sha256"],
                        shard)

    failed = None
    with open_executor(cfg.executor, params, uses_cuda(cfg.device, validate_cfg.device)) as executor:
        try:
            with writer_to(out) as plans.writer, writer_to(rejected_out) as plans.rejected_writer, \
                    tqdm(total=plans.wanted, desc=f"expand {task.name}", unit="trajectory") as plans.bar, \
                    every_unit(executor, "expand"):
                for w in (plans.writer, plans.rejected_writer):
                    if w is not None:
                        copy_scene(src, w)
                for _ in drive(executor, [plans], cfg.batches_in_flight):
                    pass
        except UnitsFailed as err:
            failed = err
    where = ((str(local.device), local.environment) if cfg.executor == "local"  # ray: where a unit ran, if one did
             else (plans.device or cfg.device, plans.environment or environment_info("cpu")))
    result = {**_report(plans, cfg, sources, checkpoint, store, out, rejected_out, phash, executor.report(), *where,
                        time.perf_counter() - started), "engine": "batches"}
    write_json_atomic(report, result)
    if failed is not None:
        raise failed
    return result


def _report(plans: ExpandPlans | SlotExpansion, cfg: ExpandConfig, sources: list[SourceEpisode], checkpoint: dict[str, Any],
            store: Path, out: Path, rejected_out: Path | None, phash: str, executor: dict[str, Any],
            device: str, environment: dict[str, str], wall: float) -> dict[str, Any]:
    """The stage's report (reports/expand.json)."""
    accepted, generated, counters = plans.accepted, plans.generated, plans.counters
    untangle = {**counters["untangle"], **({"then": counters["then"]} if "then" in counters else {})} \
        if "untangle" in counters else None
    return {
        "task": plans.task.name,
        "source_episodes": len(sources),
        "sources": [{"episode": s.eid, "cell": s.cell, "presettle_state": s.presettle} for s in sources],
        "projection": cfg.projection,
        "pad_carry": cfg.pad_carry,
        "projection_stats": counters.get("projection"),  # None when no batch ran
        "untangle": cfg.untangle,
        "self_contact": cfg.self_contact,
        "untangle_stats": untangle,
        "target_trajectories": cfg.target_trajectories,
        "wanted_generated": plans.wanted,
        "attempts": plans.attempts,
        "infeasible_plans": len(plans.infeasible),
        "generated": generated,
        "accepted": accepted,
        "rejected": generated - accepted,
        "rejections": plans.rejections,
        "acceptance_rate": accepted / generated if generated else None,
        "expanded_total": len(sources) + accepted,
        "target_reached": len(sources) + accepted >= cfg.target_trajectories,
        "frames_generated": plans.frames,
        "rollout_s": plans.rollout_s,
        "model_frames_per_s": plans.frames / plans.rollout_s if plans.rollout_s else None,
        "wall_s": wall,
        "stopped_early": accepted < plans.wanted and plans.attempts < cfg.max_attempts,
        "trajectories_per_min": 60.0 * generated / wall,
        "accepted_per_min": 60.0 * accepted / wall,
        "coverage": plans.planner.coverage(plans.task),
        "rejected_episodes": plans.rejected,
        "infeasible": plans.infeasible,
        "device": device,
        "executor": executor,
        "model": checkpoint,
        "store": str(store),
        "out": str(out),
        "rejected_out": str(rejected_out) if rejected_out is not None else None,
        "params_hash": phash,
        "environment": environment,
    }


def expand_summary(r: dict[str, Any]) -> str:
    """The line `python -m stages.expand` prints."""
    failed = ", ".join(f"{k} {v}" for k, v in r["rejections"].items() if v) or "none"
    return (f"expand {r['task']}: {r['accepted']}/{r['generated']} generated episodes accepted "
            f"({r['infeasible_plans']} plans infeasible); rejected: {failed}; {r['expanded_total']}/"
            f"{r['target_trajectories']} trajectories with the {r['source_episodes']} source ones"
            f"{'' if r['target_reached'] else ' (target NOT reached)'}; {r['trajectories_per_min']:.2f} generated/min "
            f"on {r['device']}, {r['wall_s']:.1f} s" + _overflow_warning(r.get("projection_stats")))


def _overflow_warning(stats: dict[str, float] | None) -> str:
    """A warning when the slot engine's pair capacities overflowed: the near pairs left out are neither bounded nor
    kept apart, and the bag then tends to slip out of the pads (reports/gpu/expand_settings_accuracy.md)."""
    dropped = (stats or {}).get("pairs_dropped") or 0
    return (f"; WARNING: {dropped:,.0f} near cloth pairs did not fit the slot engine's capacities: raise "
            "expand.slots.pair_capacity / self_contact_capacity" if dropped else "")
