"""Scenes of a trajectory store's episodes: rebuilt from params `scene` once per distinct layout (the predicted
objects and the held ones) and checked against the meshes the store holds, so a changed `scene` section fails loudly.
Used wherever stored episodes are replayed, checked or expanded (validate, evaluate, expand)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from wc.data.store import TrajectoryStore
from wc.scene.config import SceneConfig
from wc.scene.scene import Scene, build_scene

MESH_ATOL_M = 1e-6  # rebuilt rest meshes must match the store's to this


Layout = tuple[tuple[str, ...], tuple[tuple[str, str, tuple[float, ...]], ...]]


def episode_held(attrs: Mapping[str, Any], where: str) -> dict[str, tuple[str, tuple[float, ...]]]:
    """The `held` attr of an episode as {object: (link, local pose (7,))}; {} when it holds nothing."""
    held = attrs.get("held") or {}
    if not isinstance(held, Mapping):
        raise ValueError(f"{where}: attr 'held' must map object names to {{link, local_pose}}, got {held!r}")
    out = {}
    for name, spec in held.items():
        pose = spec.get("local_pose") if isinstance(spec, Mapping) else None
        link = spec.get("link") if isinstance(spec, Mapping) else None
        if not isinstance(link, str) or not isinstance(pose, (list, tuple)) or len(pose) != 7:
            raise ValueError(f"{where}: attr held.{name} must be {{link: str, local_pose: [7 floats]}}, got {spec!r}")
        out[name] = (link, tuple(float(p) for p in pose))
    return out


class EpisodeScenes:
    """Scenes of a store's episodes, rebuilt from params `scene` once per distinct layout (objects, held)
    and checked against the meshes the store holds (a changed `scene` section fails loudly)."""

    def __init__(self, scene_cfg: SceneConfig, store: TrajectoryStore) -> None:
        self.scene_cfg = scene_cfg
        self.store = store
        self._scenes: dict[Layout, Scene] = {}

    def layout(self, eid: str) -> Layout:
        held = episode_held(self.store.episode_attrs(eid), f"{self.store.path}: episode {eid}")
        held_key = tuple((name, link, pose) for name, (link, pose) in sorted(held.items()))
        return tuple(self.store.episode_objects(eid)), held_key

    def scene(self, eid: str) -> Scene:
        key = self.layout(eid)
        if key not in self._scenes:
            objects, held = key
            scene = build_scene(self.scene_cfg, objects, held={n: (link, pose) for n, link, pose in held})
            self._check_meshes(scene)
            self._scenes[key] = scene
        return self._scenes[key]

    def _check_meshes(self, scene: Scene) -> None:
        stored = {n: (o.rest_positions, o.faces) for n, o in self.store.objects.items()}
        stored.update({n: (p.local_points, None) for n, p in self.store.prescribed.items() if n.startswith("held_")})
        built = {n: (m.vertices, m.faces) for n, m in scene.objects.items()}
        built.update({n: (h.mesh.vertices, None) for n, h in scene.held.items()})
        for name, (vertices, faces) in built.items():
            if name not in stored:
                continue
            v, f = stored[name]
            same = v.shape == vertices.shape and np.allclose(v, vertices, atol=MESH_ATOL_M)
            if not same or (f is not None and not np.array_equal(f, faces)):
                raise ValueError(f"{self.store.path}: {name!r} rebuilt from params `scene` ({len(vertices)} vertices) "
                                 f"differs from the store's ({len(v)} vertices): the scene params changed since "
                                 "the simulate stage wrote this store; re-run simulate")
