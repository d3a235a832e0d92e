"""The data-generation agent: Reset -> Execute -> Validate -> Accept, `sim.worlds` episodes per batch.

Reset samples the initial state, lets it settle under the robot's start posture and prepares frame
0; Execute rolls the open-loop action program out in the Newton simulator; Validate runs the named
physical and visual checks (wc.validate) and then the task's own check; the first failure is
logged with its frame and fed back to the planner, which remembers it across runs.
"""

from __future__ import annotations

import time

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from wc.agent.memory import MODES as MEMORY_MODES
from wc.agent.planner import Planner
from wc.distributed import LocalExecutor, Unit, WorkerSpec, check_executor, drive
from wc.reports import environment_info
from wc.data.store import TrajectoryWriter
from wc.dynamics import ObjectState
from wc.scene.config import SceneConfig
from wc.scene.scene import OBJECT_KINDS, Scene, build_scene
from wc.seeds import episode_seed
from wc.sim.config import SimConfig
from wc.sim.kinematic import pose_twists, transform_points
from wc.sim.newton_sim import NewtonSimulator
from wc.tasks.base import UNREACHABLE, EpisodeSpec, InfeasibleEpisode, Task
from wc.tasks.motion import ARM_COLUMNS
from wc.validate import ValidateConfig, first_failure


@dataclass(frozen=True)
class AgentConfig:
    tasks: tuple[str, ...]  # task programs to run, by registered name
    episodes_per_task: int  # accepted episodes wanted per task
    max_attempts_per_task: int  # give up on a task after this many episodes
    seed: int  # stage seed; episode seeds derive from it
    workers: int = 1  # local executor: tasks run at once, one process each; 1: in the calling process (same episodes)
    executor: str = "local"  # local: as `workers` says; ray / processes: every task's batches as Ray tasks / in
    # one process per GPU (wc.distributed)
    batches_in_flight: int = 1  # batches of a task proposed before the earlier ones' verdicts are filed (1: each
    # proposal sees every earlier verdict); the episodes depend on it, not on the executor
    memory: str = "fresh"  # fresh: the planner starts from no outcomes (the episodes depend on params and seed alone);
    # kept: from the memory file's, left by earlier runs (the episodes then depend on that history)

    def validate(self) -> None:
        check_executor(self.executor)
        if self.memory not in MEMORY_MODES:
            raise ValueError(f"memory must be fresh or kept, got {self.memory!r}")
        if self.batches_in_flight < 1:
            raise ValueError(f"batches_in_flight must be >= 1, got {self.batches_in_flight}")
        if not self.tasks:
            raise ValueError("tasks must name at least one task")
        repeated = sorted({t for t in self.tasks if self.tasks.count(t) > 1})
        if repeated:
            raise ValueError(f"tasks must not repeat, got {repeated} more than once")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.episodes_per_task < 1:
            raise ValueError(f"episodes_per_task must be >= 1, got {self.episodes_per_task}")
        if self.max_attempts_per_task < self.episodes_per_task:
            raise ValueError(f"max_attempts_per_task ({self.max_attempts_per_task}) must be >= "
                             f"episodes_per_task ({self.episodes_per_task})")


@dataclass
class EpisodeRecord:
    """One executed episode; arrays are None when it could not be planned (first_failure 'unreachable')
    or blew up before it could be stored."""

    spec: EpisodeSpec
    first_failure: str | None
    failure_frame: int | None = None
    x: np.ndarray | None = None  # (T, N, 3), objects in `layout['objects']` order
    v: np.ndarray | None = None
    action: np.ndarray | None = None  # (T, 14)
    link_poses: np.ndarray | None = None  # (T, L, 7), columns `layout['links']`
    env_poses: np.ndarray | None = None  # (T, E, 7)
    layout: dict[str, Any] = field(default_factory=dict)  # store attrs: objects, links, held, handoff


@dataclass
class TaskWorld:
    """A task's scenes and simulators. `scene` is what is recorded (every object the task predicts,
    plus what the robot holds); `sim` simulates it, except that objects handed off from the gripper
    are held in `sim` and predicted in `free_sim` from the release frame on."""

    task: Task
    scene: Scene
    sim_scene: Scene
    sim: NewtonSimulator
    free_sim: NewtonSimulator | None = None

    @property
    def solver_steps(self) -> int:
        return self.sim.solver_steps + (self.free_sim.solver_steps if self.free_sim else 0)


def build_task_world(scene_cfg: SceneConfig, sim_cfg: SimConfig, task: Task) -> TaskWorld:
    held = task.held()
    handoff = tuple(getattr(task, "handoff", ()))
    unknown = [o for o in handoff if o not in held or o not in task.objects]
    if unknown:
        raise ValueError(f"task {task.name}: handoff objects {unknown} must be both held and predicted")
    scene = build_scene(scene_cfg, task.objects, held=held)
    if not handoff:
        return TaskWorld(task, scene, scene, NewtonSimulator(scene, sim_cfg))
    sim_scene = build_scene(scene_cfg, [o for o in task.objects if o not in handoff], held=held)
    free_scene = build_scene(scene_cfg, task.objects)
    return TaskWorld(task, scene, sim_scene, NewtonSimulator(sim_scene, sim_cfg), NewtonSimulator(free_scene, sim_cfg))


def store_scene(scene_cfg: SceneConfig, tasks: list[Task]) -> Scene:
    """Every object any task predicts or holds: the store's objects and prescribed sample sets."""
    objects = [n for n in OBJECT_KINDS if any(n in t.objects for t in tasks)]
    held: dict[str, tuple] = {}
    for task in tasks:
        held.update(task.held())
    return build_scene(scene_cfg, objects, held={n: held[n] for n in OBJECT_KINDS if n in held})


@contextmanager
def simulator_store(path: str | Path, scene_cfg: SceneConfig, sim_cfg: SimConfig, tasks: list[Task],
                    params_hash: str, created_by: str) -> Iterator[tuple[TrajectoryWriter, Scene]]:
    """``with simulator_store(...) as (writer, scene)``: an atomic trajectory store for episodes these tasks
    simulate, its scene (`store_scene`, each object with its simulated material) already added; frame dt and
    substeps of sim_cfg."""
    union = store_scene(scene_cfg, tasks)
    with TrajectoryWriter(path, dt=sim_cfg.frame_dt_s, substeps=sim_cfg.substeps, params_hash=params_hash,
                          created_by=created_by, object_order=list(union.objects),
                          link_names=list(union.link_names), env_names=list(union.env_names)) as writer:
        writer.add_scene(union, {name: getattr(sim_cfg, name).__dict__ for name in union.objects})
        yield writer, union


def pad_to_length(actions: np.ndarray, length: int) -> np.ndarray:
    """Hold the last action until the episode has `length` frames."""
    return np.concatenate([actions, np.repeat(actions[-1:], length - len(actions), axis=0)])


def release_frame(task: Task, actions: np.ndarray) -> int:
    """First frame at which the gripper holding the handed-off objects starts to open."""
    link = task.held()[task.handoff[0]][0]
    column = ARM_COLUMNS[link.split("_", 1)[0]][1]
    opening = np.flatnonzero(actions[:, column] > actions[0, column] + 1e-6)
    if not len(opening):
        raise InfeasibleEpisode(f"{task.name}: the gripper holding {task.handoff} never opens")
    return int(opening[0])


def hold_until(actions: np.ndarray, frame: int, release: int) -> np.ndarray:
    """Insert holds before `frame` so the release happens at frame `release`."""
    return np.concatenate([actions[:frame], np.repeat(actions[frame - 1:frame], release - frame, axis=0),
                           actions[frame:]])


def layout_attrs(world: TaskWorld, release: int | None) -> dict[str, Any]:
    scene = world.scene
    attrs: dict[str, Any] = {"objects": list(scene.objects), "links": list(scene.link_names)}
    if scene.held:
        attrs["held"] = {h.mesh.name: {"link": h.link, "local_pose": h.local_pose.tolist()}
                         for h in scene.held.values()}
    if release is not None:
        attrs["handoff"] = {name: release for name in world.task.handoff}
    return attrs


def _held_state(scene: Scene, name: str, poses: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and velocities (T, M, 3) of a held object posed by link_poses (T, L, 7)."""
    column = scene.link_names.index(f"held_{name}")
    pose = poses[:, column]
    local = scene.held[f"held_{name}"].mesh.vertices
    x = transform_points(pose, local)
    twist = pose_twists(np.concatenate([pose[:1], pose[:-1]]), pose, dt)
    r = x - pose[:, None, :3]
    return x, twist[:, None, :3] + np.cross(twist[:, None, 3:], r)


def _assemble(scene: Scene, rows: dict[str, slice], simulated: tuple[np.ndarray, np.ndarray],
              held: dict[str, tuple[np.ndarray, np.ndarray]], frames: int | slice
              ) -> tuple[np.ndarray, np.ndarray]:
    """x, v at `frames` in `scene`'s object order, from simulated (x, v) with object rows `rows`
    and the held objects' (x, v)."""
    out = []
    for k in range(2):
        parts = {n: simulated[k][frames, r] for n, r in rows.items()} | {n: h[k][frames] for n, h in held.items()}
        out.append(np.concatenate([parts[name] for name in scene.objects], axis=-2).astype(np.float32))
    return out[0], out[1]


def execute(world: TaskWorld, states: list[ObjectState], actions: list[np.ndarray],
             on_frame: Callable[[], None] | None) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray], int | None]:
    """Roll out a batch; returns [(x, v)] in the recording layout, the (possibly re-timed) actions and
    the release frame of a hand-off (None without one)."""
    task, sim = world.task, world.sim
    if world.free_sim is None:
        length = max(len(a) for a in actions)
        actions = [pad_to_length(a, length) for a in actions]
        return sim.rollout_batch(states, actions, on_frame=on_frame), actions, None
    releases = [release_frame(task, a) for a in actions]
    release = max(releases)
    actions = [hold_until(a, k, release) for a, k in zip(actions, releases)]
    length = max(len(a) for a in actions)
    actions = [pad_to_length(a, length) for a in actions]
    before = sim.rollout_batch(states, [a[:release + 1] for a in actions], on_frame=on_frame)
    dt = sim.cfg.frame_dt_s
    poses = [world.scene.link_poses(a) for a in actions]
    held = [{name: _held_state(world.scene, name, p, dt) for name in task.handoff} for p in poses]
    rows = world.sim_scene.vertex_slices()
    free_scene = world.free_sim.scene
    starts = [ObjectState(*_assemble(free_scene, rows, sim_xv, h, release)) for sim_xv, h in zip(before, held)]
    after = world.free_sim.rollout_batch(starts, [a[release:] for a in actions], on_frame=on_frame)
    out = []
    for sim_xv, h, (xb, vb) in zip(before, held, after):
        x, v = _assemble(world.scene, rows, sim_xv, h, slice(0, release))
        out.append((np.concatenate([x, xb]), np.concatenate([v, vb])))
    return out, actions, release


def reset_batch(world: TaskWorld, specs: list[EpisodeSpec]
                ) -> tuple[list[tuple[EpisodeSpec, ObjectState, np.ndarray]], list[EpisodeSpec]]:
    """Reset: sample, settle (one simulator batch) and prepare each episode, then plan its actions.
    Returns the runnable (spec, frame-0 state, actions (T, 14)) and the specs that cannot be planned."""
    task, scene, sim = world.task, world.sim_scene, world.sim
    planned, unreachable = [], []
    for spec in specs:
        rng = np.random.default_rng(spec.seed)
        try:
            initial = task.initial_state(scene, spec, rng)
            planned.append((spec, rng, initial, task.settle_action(scene, spec, initial)))
        except InfeasibleEpisode:
            unreachable.append(spec)
    settled = [p[2] for p in planned]
    if planned and task.settle:
        settled = sim.settle(settled, [p[3] for p in planned], sim.cfg.settle_s)
    runnable = []
    for (spec, rng, _, start), state in zip(planned, settled):
        try:
            state = task.prepare(scene, state, spec, rng)
            runnable.append((spec, state, task.actions(scene, state, spec, start, sim.cfg.frame_dt_s)))
        except InfeasibleEpisode:
            unreachable.append(spec)
    return runnable, unreachable


def judge(world: TaskWorld, spec: EpisodeSpec, x: np.ndarray, v: np.ndarray, action: np.ndarray,
          link_poses: np.ndarray, cfg: ValidateConfig, frame_dt_s: float) -> tuple[str, int] | None:
    """First failing check: the physical and visual predicates, then the task's own verdict (last frame)."""
    failure = first_failure(world.scene, x, v, action, link_poses, cfg, frame_dt_s=frame_dt_s)
    if failure is not None:
        return failure
    verdict = world.task.check(world.scene, spec, x, action)
    return (verdict, len(x) - 1) if verdict else None


def simulate_batch(world: TaskWorld, specs: list[EpisodeSpec], validate_cfg: ValidateConfig,
                   on_frame: Callable[[], None] | None = None) -> list[EpisodeRecord]:
    """Reset, Execute and Validate one batch of proposed episodes (at most `sim.worlds`): a record per spec, the
    unplannable ones (UNREACHABLE) first, then the others in `specs` order. What a worker does; the planner that
    proposed the specs is told the verdicts by the caller."""
    scene, sim = world.sim_scene, world.sim
    runnable, unreachable = reset_batch(world, specs)
    records = [EpisodeRecord(spec, UNREACHABLE) for spec in unreachable]
    if not runnable:
        return records
    results, actions, release = execute(world, [r[1] for r in runnable], [r[2] for r in runnable], on_frame)
    env = np.repeat(scene.env_poses()[None], len(actions[0]), axis=0)
    for (spec, _, _), act, (x, v) in zip(runnable, actions, results):
        poses = world.scene.link_poses(act)
        failure = judge(world, spec, x, v, act, poses, validate_cfg, sim.cfg.frame_dt_s)  # Validate
        name, frame = failure if failure else (None, None)
        if name == "non_finite":  # nothing storable
            records.append(EpisodeRecord(spec, name, frame))
            continue
        records.append(EpisodeRecord(spec, name, frame, x, v, act, poses, env, layout_attrs(world, release)))  # Accept
    return records


@dataclass
class BatchResult:
    """What one batch (a simulate work unit) gives back to the task's planner."""

    records: list[EpisodeRecord]  # simulate_batch's, one per spec
    solver_steps: int  # Newton solver steps it took
    wall_s: float
    table_top_z: float  # [m], for the lift curves
    environment: dict[str, str]  # where it ran (wc.reports.environment_info)


class BatchSimulator:
    """A simulate work unit's worker: a task's world simulating batches of proposed episodes."""

    def __init__(self, world: TaskWorld, validate_cfg: ValidateConfig,
                 on_frame: Callable[[], None] | None = None) -> None:
        self.world, self.validate_cfg, self.on_frame = world, validate_cfg, on_frame
        self.environment = environment_info(world.sim.device)

    def __call__(self, specs: list[EpisodeSpec]) -> BatchResult:
        started, steps = time.perf_counter(), self.world.solver_steps
        records = simulate_batch(self.world, specs, self.validate_cfg, self.on_frame)
        return BatchResult(records, self.world.solver_steps - steps, time.perf_counter() - started,
                           float(self.world.scene.table.top_z), self.environment)


class TaskAttempts:
    """The planner's side of one task's episodes, a stream of batches (wc.distributed.streams): the planner
    proposes each batch from every verdict filed before it, and the verdicts are filed in proposal order, so the
    planner and the failure memory see the same verdicts in the same order on any executor (workers only
    simulate). Stops proposing once the accepted episodes plus those in flight reach `wanted`, after `max_attempts`,
    or after `deadline` (time.time() seconds)."""

    def __init__(self, task: Task, planner: Planner, task_index: int, worlds: int, wanted: int, max_attempts: int,
                 stage_seed: int, worker: WorkerSpec, deadline: float | None = None) -> None:
        self.task, self.planner, self.task_index, self.worlds = task, planner, task_index, worlds
        self.wanted, self.max_attempts, self.stage_seed, self.worker = wanted, max_attempts, stage_seed, worker
        self.deadline = deadline
        self.attempts = self.accepted = self.in_flight = self.solver_steps = 0
        self.records: list[EpisodeRecord] = []  # filed, in the order they ran
        self.wall_s, self.table_top_z = 0.0, float("nan")
        self.environment: dict[str, str] | None = None  # where the last batch ran

    def next_unit(self) -> Unit | None:
        if not (self.accepted + self.in_flight < self.wanted and self.attempts < self.max_attempts
                and (self.deadline is None or time.time() < self.deadline)):
            return None
        batch = min(self.worlds, self.max_attempts - self.attempts)
        specs = [self.planner.propose(self.task, episode_seed(self.stage_seed, self.task_index, self.attempts + i))
                 for i in range(batch)]
        label = f"task {self.task.name} attempts {self.attempts}-{self.attempts + batch - 1}"
        self.attempts += batch
        self.in_flight += batch
        return Unit(self.worker, specs, label)

    def file(self, result: BatchResult) -> None:
        self.in_flight -= len(result.records)
        for record in result.records:
            self.planner.record(record.spec, record.first_failure, record.failure_frame)
            self.accepted += record.first_failure is None
        self.records += result.records
        self.solver_steps += result.solver_steps
        self.wall_s += result.wall_s
        self.table_top_z, self.environment = result.table_top_z, result.environment


def run_episodes(world: TaskWorld, planner: Planner, task_index: int, wanted: int, max_attempts: int,
                 stage_seed: int, validate_cfg: ValidateConfig, on_frame: Callable[[], None] | None = None,
                 deadline: float | None = None, batches_in_flight: int = 1) -> Iterator[EpisodeRecord]:
    """Simulate episodes of one task in this process, `sim.worlds` at a time, until `wanted` are accepted or
    `max_attempts` were tried; yields each with its verdict (the planner's side: wc.agent.attempts). With several
    worlds every batch is full (an idle world costs a GPU step as much as a busy one), so a task may end with more
    than `wanted` accepted. `deadline` (time.time() seconds): no batch starts after it (a chunked GPU job keeps what
    it simulated)."""
    simulator = BatchSimulator(world, validate_cfg, on_frame)
    attempts = TaskAttempts(world.task, planner, task_index, world.sim.worlds, wanted, max_attempts, stage_seed,
                            WorkerSpec(world.task.name, lambda: simulator), deadline)
    for _ in drive(LocalExecutor(), [attempts], batches_in_flight):
        pass
    yield from attempts.records
