"""Planning generated episodes: a source episode's settled frame 0, rigidly moved, and the task program's
action sequence for a spec the coverage planner proposes.

The frame-0 robot posture follows the simulator agent's rule (wc.agent.runner.reset_batch): the task's
settle_action of the state *before* settling. A source episode's pre-settle state is redrawn from its seed
(task.initial_state), accepted when its settle posture reproduces the stored frame-0 action, and moved with the
same rigid motion as the settled state. A plan whose frame-0 state already penetrates that posture (the parent
settled under another posture, e.g. another grasp cell's wrist where the parent's handle hangs) is infeasible.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from wc.data.store import TrajectoryStore
from wc.dynamics import ObjectState
from wc.expand.config import ExpandConfig
from wc.expand.transform import check_on_table, planar_transform
from wc.scene.scene import Scene
from wc.seeds import SeedStream, episode_seed
from wc.tasks.base import EpisodeSpec, InfeasibleEpisode, Task
from wc.validate.config import ValidateConfig
from wc.validate.predicates import Episode, cloth_rows, penetration, table_and_robot_distance
from wc.scene.episode_scenes import EpisodeScenes

LAYOUT_ATTRS = ("objects", "links", "held")  # episode attrs a generated episode inherits from its parent
START_TOL = 1e-4  # rad or m: a redrawn pre-settle state must reproduce the stored frame-0 action this closely


class NoSourceEpisodesError(ValueError):
    """The source store holds no accepted episode of the task to expand."""


@dataclass(frozen=True)
class SourceEpisode:
    """Frame 0 (settled, as the simulator recorded it) of one source episode of the task."""

    eid: str
    cell: int
    x0: np.ndarray  # (N, 3) m, the episode's objects
    layout: dict[str, Any]  # its layout attrs (objects, links, held), inherited by generated episodes
    x_initial: np.ndarray  # (N, 3) m, the state before settling the frame-0 posture was planned on (x0 if unknown)
    presettle: bool = False  # x_initial was redrawn and reproduces the stored frame-0 action


@dataclass(frozen=True)
class PlannedEpisode:
    """A generated episode before its rollout: the new frame-0 state and the commanded actions."""

    spec: EpisodeSpec
    parent: str  # source episode id
    yaw_deg: float  # applied yaw about the bag's vertical centroid axis
    shift_m: tuple[float, float]  # applied xy shift
    x0: np.ndarray  # (N, 3) m; v0 = 0
    actions: np.ndarray  # (T, 14)


def source_episodes(store: TrajectoryStore, task: Task, scenes: EpisodeScenes, limit: int = 0
                    ) -> tuple[list[SourceEpisode], Scene]:
    """The accepted episodes of `task` in `store` (frame 0 only; the first `limit` in store order, 0: all) and their
    common scene; NoSourceEpisodesError when there is none, ValueError when their layout is not the task's."""
    ids = store.episodes_where(task=task.name, accepted=True)[:limit or None]
    if not ids:
        tasks = sorted({store.episode_attrs(e)["task"] for e in store.episode_ids})
        raise NoSourceEpisodesError(f"{store.path}: no accepted episode of task {task.name!r} to expand "
                                    f"(tasks in the store: {tasks})")
    if task.handoff:
        raise ValueError(f"expand: task {task.name!r} hands objects off ({task.handoff}); not supported")
    layouts = {scenes.layout(e) for e in ids}
    if len(layouts) != 1:
        raise ValueError(f"{store.path}: episodes of {task.name!r} have {len(layouts)} different layouts {layouts}")
    scene = scenes.scene(ids[0])
    if tuple(scene.objects) != tuple(task.objects):
        raise ValueError(f"{store.path}: episodes of {task.name!r} predict {list(scene.objects)}, the task program "
                         f"{list(task.objects)}")
    out = []
    for eid in ids:
        attrs = store.episode_attrs(eid)
        first = store.read_window(eid, 0, 1, ("x", "action"))
        x0 = first["x"][0]
        initial = presettle_state(task, scene, attrs, x0, first["action"][0])
        out.append(SourceEpisode(eid, int(attrs["cell"]), x0, {k: attrs[k] for k in LAYOUT_ATTRS if k in attrs},
                                 x0 if initial is None else initial, initial is not None))
    return out, scene


def presettle_state(task: Task, scene: Scene, attrs: dict[str, Any], x0: np.ndarray, action0: np.ndarray
                    ) -> np.ndarray | None:
    """A source episode's objects before settling (N, 3), redrawn as the simulator agent drew them (the task's
    initial_state from the episode's seed); None unless its settle posture reproduces the stored frame-0 action
    (a store not made by the agent, or task params changed since)."""
    spec = EpisodeSpec(str(attrs["task"]), int(attrs["seed"]), int(attrs["cell"]), float(attrs["speed"]),
                       float(attrs["amplitude"]))
    try:
        initial = task.initial_state(scene, spec, np.random.default_rng(spec.seed))
        start = task.settle_action(scene, spec, initial)
    except InfeasibleEpisode:
        return None
    if initial.x.shape != x0.shape or not np.allclose(start, action0, atol=START_TOL):
        return None
    return initial.x


def plan_seed(stage_seed: int, shard: int, attempt: int) -> int:
    """The seed of generated episode `attempt` of shard `shard` (expand.shards), in the expand seed stream. Expand has
    one task: the task coordinate of the seed is the shard's, so shard 0 draws what an unsharded run draws."""
    return episode_seed(stage_seed, shard, attempt, SeedStream.EXPAND)


def pick_parent(sources: list[SourceEpisode], cell: int, attempt: int) -> SourceEpisode:
    """The source episode a generated episode of `cell` starts from: those of the same cell in turn (settled
    under nearly the same posture), else all of them in turn."""
    same = [s for s in sources if s.cell == cell] or sources
    return same[attempt % len(same)]


def check_clear_at_start(scene: Scene, x0: np.ndarray, start: np.ndarray, cfg: ValidateConfig) -> None:
    """InfeasibleEpisode when frame 0 (objects x0 (N, 3), robot at action start (14,)) already fails the
    validation's penetration check: no rollout could pass."""
    link_poses = scene.link_poses(start[None])
    ep = Episode(x0[None], np.zeros_like(x0)[None], start[None], link_poses, 1.0)
    if penetration(scene, ep, cfg) is None:
        return
    depth = -table_and_robot_distance(scene, x0[None, cloth_rows(scene)], link_poses).min()
    raise InfeasibleEpisode(f"the planned frame-0 state penetrates a collision body at its start posture (deepest "
                            f"into the table or the robot: {depth * 1e3:.1f} mm; tolerance "
                            f"{cfg.penetration_tol_m * 1e3:.1f} mm): the parent settled under another posture")


def cell_yaw_offset_deg(task: Task, parent_cell: int, cell: int) -> float:
    """Yaw [deg] that turns the parent's cell yaw bin into the new cell's, for tasks whose cells bin the
    initial yaw (`yaw_bins_deg`); 0 otherwise."""
    values = getattr(task, "cell_values", None)
    if values is None or "yaw_bins_deg" not in values(cell):
        return 0.0
    return float(values(cell)["yaw_bins_deg"] - values(parent_cell)["yaw_bins_deg"])


def plan_episode(task: Task, scene: Scene, source: SourceEpisode, spec: EpisodeSpec, cfg: ExpandConfig,
                 frame_dt_s: float, validate_cfg: ValidateConfig) -> PlannedEpisode:
    """Move the source's frame 0 (and its pre-settle state) rigidly (yaw, shift drawn from spec.seed) and plan
    the task's actions on it; InfeasibleEpisode when the state leaves the table's sampled region, the robot
    cannot follow the plan, or frame 0 already penetrates the start posture (check_clear_at_start)."""
    rng = np.random.default_rng(spec.seed)
    yaw = cell_yaw_offset_deg(task, source.cell, spec.cell) + float(rng.uniform(*cfg.yaw_range_deg))
    shift = (float(rng.uniform(*cfg.shift_x_range_m)), float(rng.uniform(*cfg.shift_y_range_m)))
    centre = np.asarray(source.x0, np.float64)[:, :2].mean(axis=0)  # one rigid motion for both states
    x0 = planar_transform(source.x0, yaw, shift, centre)
    check_on_table(x0, scene.table)
    initial = planar_transform(source.x_initial, yaw, shift, centre)
    start = task.settle_action(scene, spec, ObjectState(initial, np.zeros_like(initial)))  # as the simulator does
    state = task.prepare(scene, ObjectState(x0, np.zeros_like(x0)), spec, rng)
    actions = task.actions(scene, state, spec, start, frame_dt_s)
    check_clear_at_start(scene, state.x, actions[0], validate_cfg)
    return PlannedEpisode(spec, source.eid, yaw, shift, state.x, actions)
