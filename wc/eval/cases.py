"""Evaluation cases: which stored phases are rolled out, and everything a rollout and its scoring need.

A case is one phase (wc.train.data.episode_phases: a hand-off episode has two) read from a start frame (its first,
unless asked otherwise): the recorded x, v, commanded actions and prescribed body poses, the frames of the same
layout recorded before the start (up to the reader's `past_frames`: what a model of past frames is given, as in
training; a held-out block's start has the episode's frames before it), the model's scene layout, and the collision scene (table, robot boxes, rigid and held objects) rebuilt
from params `scene` for that phase.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from wc.data.store import TrajectoryStore
from wc.dynamics import ObjectState
from wc.model.learned_dynamics import RecordedPast
from wc.model.layout import SceneLayout, scene_layout
from wc.scene.config import SceneConfig
from wc.scene.scene import Scene, build_scene
from wc.train.config import TrainConfig
from wc.train.data import LayoutKey, Phase, episode_phases, layout_phase_start, phases_of, read_phase_window
from wc.train.loop import prepare_data
from wc.validate.predicates import cloth_rows
from wc.scene.episode_scenes import EpisodeScenes, episode_held


@dataclass(frozen=True)
class Case:
    """T frames of one phase from frame `start`: x, v (T, N, 3), the commanded actions (T, 14), poses (T, P, 7) of
    layout.bodies as recorded, link_poses (T, L, 7) in scene.link_names order, cloth_area (N_cloth,) m^2 of the
    scene's cloth rows; past_x, past_v (K, N, 3) and past_poses (K, P, 7) the K phase frames recorded before
    `start` in the episode's phase of this layout (K = 0 at its first frame)."""

    phase: Phase
    task: str
    layout: SceneLayout
    scene: Scene
    x: np.ndarray
    v: np.ndarray
    actions: np.ndarray
    poses: np.ndarray
    link_poses: np.ndarray
    cloth_area: np.ndarray
    start: int
    past_x: np.ndarray
    past_v: np.ndarray
    past_poses: np.ndarray

    @property
    def steps(self) -> int:
        return len(self.x) - 1

    def recorded_past(self) -> RecordedPast | None:
        """What a model of past frames is given from the recorded start state (None without past frames)."""
        if not len(self.past_x):
            return None
        return RecordedPast(self.past_x, self.past_v, self.past_poses, ObjectState(self.x[0], self.v[0]))


def held_out_phases(store: TrajectoryStore, train_cfg: TrainConfig) -> tuple[list[Phase], str]:
    """(phases, where they come from): the test split; without one, the validation data training held out
    (wc.train.loop.prepare_data: the val split, else its held-out part of the train episodes)."""
    test = phases_of(store, "test")
    if test:
        return test, "test split"
    data = prepare_data(store, train_cfg)
    return data.val_phases, f"no test split; training's validation data: {data.validation}"


def long_phases(store: TrajectoryStore, per_task: int) -> tuple[list[Phase], str]:
    """(phases, where they come from): per task the `per_task` longest phases of test episodes, or of every
    episode when the store has no test split; ties go to the lower episode id."""
    episodes = store.episodes_where(split="test")
    source = "test split"
    if not episodes:
        episodes, source = store.episode_ids, "every episode (the store has no test split)"
    by_task: dict[str, list[Phase]] = {}
    for eid in episodes:
        by_task.setdefault(store.episode_attrs(eid)["task"], []).extend(episode_phases(store, eid))
    picked = [p for task in sorted(by_task)
              for p in sorted(by_task[task], key=lambda p: -(p.stop - p.start))[:per_task]]
    return picked, source


class PhaseScenes(EpisodeScenes):
    """Collision scenes per phase layout: the phase's predicted objects, plus the held objects whose
    `held_<name>` body the phase prescribes (before a hand-off's release the ball is held, after it predicted)."""

    def phase_scene(self, phase: Phase) -> Scene:
        where = f"{self.store.path}: episode {phase.episode}"
        held = episode_held(self.store.episode_attrs(phase.episode), where)
        held_key = tuple((name, link, pose) for name, (link, pose) in sorted(held.items())
                         if f"held_{name}" in phase.layout[1])
        key = (phase.layout[0], held_key)
        if key not in self._scenes:
            scene = build_scene(self.scene_cfg, phase.layout[0], held={n: (link, pose) for n, link, pose in held_key})
            self._check_meshes(scene)
            self._scenes[key] = scene
        return self._scenes[key]


class CaseReader:
    """Builds cases from a store; layouts and scenes are made once per phase layout."""

    def __init__(self, store: TrajectoryStore, scene_cfg: SceneConfig, tag_scale: float, device: torch.device,
                 past_frames: int = 0) -> None:
        self.store = store
        self.past_frames = past_frames
        self.tag_scale = tag_scale
        self.device = device
        self.scenes = PhaseScenes(scene_cfg, store)
        self._layouts: dict[LayoutKey, SceneLayout] = {}

    def layout(self, key: LayoutKey) -> SceneLayout:
        if key not in self._layouts:
            self._layouts[key] = scene_layout(self.store, list(key[0]), list(key[1]), self.tag_scale).to(self.device)
        return self._layouts[key]

    def case(self, phase: Phase, frames: int, start: int | None = None) -> Case:
        """min(frames, frames left) frames of the phase from frame `start` (default: its first)."""
        start = phase.start if start is None else start
        length = min(frames, phase.stop - start)
        if start < phase.start or length < 2:
            raise ValueError(f"{self.store.path}: phase [{phase.start}, {phase.stop}) of {phase.episode} has no "
                             f"rollout from frame {start}")
        k = min(self.past_frames, start - layout_phase_start(self.store, phase))
        a = read_phase_window(self.store, phase, start - k, length + k)
        past = {key: a[key][:k] for key in ("x", "v", "poses")}
        a = {key: value[k:] for key, value in a.items()}
        scene = self.scenes.phase_scene(phase)
        links = list(phase.layout[1])
        missing = [n for n in scene.link_names if n not in links]
        if missing:
            raise ValueError(f"{self.store.path}: episode {phase.episode} has no link_poses columns for {missing}; "
                             "penetration needs every robot body and held object")
        link_poses = a["poses"][:, [links.index(n) for n in scene.link_names]]
        cloth = cloth_rows(scene)
        areas = np.concatenate([self.store.objects[o].vertex_area for o in phase.layout[0]])
        if areas.shape[0] != a["x"].shape[1]:
            raise ValueError(f"{self.store.path}: episode {phase.episode}: {a['x'].shape[1]} rows of x, "
                             f"{areas.shape[0]} vertex areas of {phase.layout[0]}")
        return Case(phase, str(self.store.episode_attrs(phase.episode)["task"]), self.layout(phase.layout), scene,
                    a["x"], a["v"], a["action"], a["poses"], link_poses, areas[cloth].astype(np.float64), start,
                    past["x"], past["v"], past["poses"])
