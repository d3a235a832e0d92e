"""A render work unit: a range of one trajectory store's episodes rendered to top and wrist views. `RenderWorker`
does it, in the stage's process (local executor) or in a Ray worker process (the store's path must be readable
there: one machine, or a shared file system); the writing stays in the stage (wc.render.stage)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from wc.config import load_section
from wc.data.store import TrajectoryStore
from wc.devices import resolve_warp_device
from wc.render.config import RenderConfig
from wc.render.geometry import episode_geometry
from wc.render.renderer import EpisodeRenderer
from wc.render.rig import check_camera_links, render_cameras
from wc.reports import environment_info
from wc.scene.config import SceneConfig


@dataclass
class RenderBatch:
    """What one render work unit gives back: each episode's views (camera -> (T, H, W, 3) uint8), in order."""

    views: list[dict[str, np.ndarray]]
    seconds: dict[str, float]  # render time per camera
    renderers_built: int  # EpisodeRenderers this unit built (one per new geometry layout)
    device: str
    environment: dict[str, str]  # where it ran (wc.reports.environment_info)


class RenderWorker:
    """The renderer of the params' `render` section: one EpisodeRenderer per geometry layout, kept for every
    store and unit this worker renders."""

    def __init__(self, params: dict[str, Any]) -> None:
        self.cfg = load_section(params, "render", RenderConfig)
        self.scene_cfg = load_section(params, "scene", SceneConfig)
        self.cameras = render_cameras(self.scene_cfg.cameras, self.cfg.cameras, self.cfg.width, self.cfg.height)
        self.device = resolve_warp_device(self.cfg.device, "render.device")
        self.environment = environment_info(self.device)
        self.by_layout: dict[tuple, EpisodeRenderer] = {}
        self._stores: dict[str, TrajectoryStore] = {}

    def frames(self, store: TrajectoryStore, eid: str) -> dict[str, np.ndarray]:
        where = f"{store.path}: episode {eid}"
        geometry = episode_geometry(store, eid, self.scene_cfg)
        check_camera_links(self.cameras, geometry.link_names, where)
        renderer = self.by_layout.get(geometry.layout)
        if renderer is None:
            renderer = EpisodeRenderer(geometry, self.cameras, self.device, self.cfg.frames_per_batch, self.cfg.shadows)
            self.by_layout[geometry.layout] = renderer
        a = store.read_episode(eid, ("x", "link_poses"))
        return renderer.render(a["x"], a["link_poses"], where)

    def seconds(self) -> dict[str, float]:
        return {n: sum(r.seconds[n] for r in self.by_layout.values()) for n in self.cameras}

    def __call__(self, payload: tuple[str, list[str]]) -> RenderBatch:
        """payload: (trajectory store path, episode ids)."""
        path, eids = payload
        if path not in self._stores:
            self._stores[path] = TrajectoryStore(path)
        store = self._stores[path]
        before, built = self.seconds(), len(self.by_layout)
        views = [self.frames(store, eid) for eid in eids]
        after = self.seconds()
        return RenderBatch(views, {n: after[n] - before[n] for n in after}, len(self.by_layout) - built, self.device,
                           self.environment)
