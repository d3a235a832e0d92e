"""Planning generated episodes: a source episode's settled frame 0, rigidly moved, and the task program's
action sequence for a spec the coverage planner proposes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from wc.data.store import TrajectoryStore
from wc.dynamics import ObjectState
from wc.expand.config import ExpandConfig
from wc.expand.transform import check_on_table, planar_transform
from wc.scene.scene import Scene
from wc.tasks.base import EpisodeSpec, Task
from wc.validate.stage import EpisodeScenes

LAYOUT_ATTRS = ("objects", "links", "held")  # episode attrs a generated episode inherits from its parent


class NoSourceEpisodesError(ValueError):
    """The source store holds no accepted episode of the task to expand."""


@dataclass(frozen=True)
class SourceEpisode:
    """Frame 0 (settled, as the simulator recorded it) of one source episode of the task."""

    eid: str
    cell: int
    x0: np.ndarray  # (N, 3) m, the episode's objects
    layout: dict[str, Any]  # its layout attrs (objects, links, held), inherited by generated episodes


@dataclass(frozen=True)
class PlannedEpisode:
    """A generated episode before its rollout: the new frame-0 state and the commanded actions."""

    spec: EpisodeSpec
    parent: str  # source episode id
    yaw_deg: float  # applied yaw about the bag's vertical centroid axis
    shift_m: tuple[float, float]  # applied xy shift
    x0: np.ndarray  # (N, 3) m; v0 = 0
    actions: np.ndarray  # (T, 14)


def source_episodes(store: TrajectoryStore, task: Task, scenes: EpisodeScenes) -> tuple[list[SourceEpisode], Scene]:
    """Every accepted episode of `task` in `store` (frame 0 only) and their common scene; NoSourceEpisodesError
    when there is none, ValueError when their layout is not the task's."""
    ids = store.episodes_where(task=task.name, accepted=True)
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
        x0 = store.read_window(eid, 0, 1, ("x",))["x"][0]
        out.append(SourceEpisode(eid, int(attrs["cell"]), x0, {k: attrs[k] for k in LAYOUT_ATTRS if k in attrs}))
    return out, scene


def cell_yaw_offset_deg(task: Task, parent_cell: int, cell: int) -> float:
    """Yaw [deg] that turns the parent's cell yaw bin into the new cell's, for tasks whose cells bin the
    initial yaw (`yaw_bins_deg`); 0 otherwise."""
    values = getattr(task, "cell_values", None)
    if values is None or "yaw_bins_deg" not in values(cell):
        return 0.0
    return float(values(cell)["yaw_bins_deg"] - values(parent_cell)["yaw_bins_deg"])


def plan_episode(task: Task, scene: Scene, source: SourceEpisode, spec: EpisodeSpec, cfg: ExpandConfig,
                 frame_dt_s: float) -> PlannedEpisode:
    """Move the source's frame 0 rigidly (yaw, shift drawn from spec.seed) and plan the task's actions on it;
    InfeasibleEpisode when the state leaves the table's sampled region or the robot cannot follow the plan."""
    rng = np.random.default_rng(spec.seed)
    yaw = cell_yaw_offset_deg(task, source.cell, spec.cell) + float(rng.uniform(*cfg.yaw_range_deg))
    shift = (float(rng.uniform(*cfg.shift_x_range_m)), float(rng.uniform(*cfg.shift_y_range_m)))
    x0 = planar_transform(source.x0, yaw, shift)
    check_on_table(x0, scene.table)
    state = ObjectState(x0, np.zeros_like(x0))
    start = task.settle_action(scene, spec, state)  # the simulator's frame-0 posture, from the state before settling
    state = task.prepare(scene, state, spec, rng)
    actions = task.actions(scene, state, spec, start, frame_dt_s)
    return PlannedEpisode(spec, source.eid, yaw, shift, state.x, actions)
