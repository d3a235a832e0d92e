"""What the cameras see in one episode: deforming object surfaces (rows of x), rigid bodies posed by
link_poses columns (robot links and fingers, held objects) and the static table, with their colours.

Colours are sRGB albedo in [0, 1]; the raytracer adds Lambert shading from a key light and ambient
light. The bag is a light fabric colour, far from the dark table and the grey robot, so it stays
distinguishable in both views; fingers are darker than the arm, so the grasp reads in the wrist view.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from wc.data.store import TrajectoryStore
from wc.scene.config import SceneConfig, TableConfig
from wc.scene.robot_geometry import LinkShape, piper_link_shapes
from wc.scene.scene import Scene, build_objects
from wc.scene.episode_scenes import episode_held

Rgb = tuple[float, float, float]

OBJECT_COLORS: dict[str, Rgb] = {"bag": (0.95, 0.80, 0.52), "sphere": (0.85, 0.18, 0.15), "cube": (0.20, 0.45, 0.85)}
DEFAULT_OBJECT_COLOR: Rgb = (0.30, 0.75, 0.35)
LINK_COLOR: Rgb = (0.66, 0.67, 0.70)
FINGER_COLOR: Rgb = (0.16, 0.16, 0.18)
TABLE_COLOR: Rgb = (0.30, 0.24, 0.20)
SIDES = ("left_", "right_")
HELD_PREFIX = "held_"


@dataclass(frozen=True)
class Surface:
    """A triangle mesh whose vertices are rows of the episode's x (cloth or predicted rigid object)."""

    name: str
    rows: slice  # rows of x (T, N_e, 3)
    faces: np.ndarray  # (F, 3) int32, indices into the rows
    color: Rgb


@dataclass(frozen=True)
class Body:
    """A rigid body posed by column `column` of the episode's link_poses (T, L_e, 7)."""

    name: str  # the link_poses column name, e.g. right_finger_a, held_cube
    column: int
    shapes: tuple[LinkShape, ...]  # primitives in the body frame (robot links)
    mesh: tuple[np.ndarray, np.ndarray] | None  # (V, 3) float32 body-frame vertices, (F, 3) int32 faces
    color: Rgb


@dataclass(frozen=True)
class EpisodeGeometry:
    surfaces: tuple[Surface, ...]
    bodies: tuple[Body, ...]
    table_center_m: tuple[float, float, float]
    table_half_extents_m: tuple[float, float, float]
    rest_positions: np.ndarray  # (N_e, 3) float32, rest shapes of the present objects (well-formed triangles)
    link_names: tuple[str, ...]  # columns of link_poses (L_e)

    @property
    def layout(self) -> tuple:
        """What fixes the renderer's model topology: episodes with equal layouts share one renderer."""
        return (tuple((s.name, s.rows.start, s.rows.stop, s.faces.tobytes()) for s in self.surfaces),
                tuple((b.name, b.column, None if b.mesh is None else b.mesh[1].tobytes()) for b in self.bodies),
                self.num_vertices, self.link_names)

    @property
    def num_vertices(self) -> int:
        return len(self.rest_positions)


@lru_cache(maxsize=8)
def _link_shapes() -> dict[str, tuple[LinkShape, ...]]:
    shapes: dict[str, list[LinkShape]] = {}
    for s in piper_link_shapes():
        shapes.setdefault(s.link, []).append(s)
    return {k: tuple(v) for k, v in shapes.items()}


def _robot_body(name: str, column: int) -> Body | None:
    """The body of a robot link column (left_link3, right_finger_a, ...), or None if it has no shapes."""
    side = next((p for p in SIDES if name.startswith(p)), None)
    shapes = _link_shapes().get(name[len(side):]) if side else None
    if not shapes:
        return None
    return Body(name, column, shapes, None, FINGER_COLOR if "finger" in name else LINK_COLOR)


def episode_geometry(store: TrajectoryStore, eid: str, scene_cfg: SceneConfig) -> EpisodeGeometry:
    """Render geometry of one stored episode. Held objects are drawn from their pose column (their mesh
    rebuilt from params `scene`) unless they are also predicted objects, whose rows of x already follow
    the held pose before the handoff."""
    where = f"{store.path}: episode {eid}"
    layout = store.episode_layout(eid)
    links = store.episode_links(eid)
    held = {}
    for obj in episode_held(store.episode_attrs(eid), where):
        if obj in layout:
            continue
        column = f"{HELD_PREFIX}{obj}"
        if column not in links:
            raise ValueError(f"{where} holds {obj!r} but has no link_poses column {column!r} (links: {links})")
        mesh = build_objects(scene_cfg, [obj])[obj]
        stored = store.prescribed.get(column)
        if stored is not None and stored.local_points.shape != mesh.vertices.shape:
            raise ValueError(f"{where}: held {obj!r} rebuilt from params `scene` has {len(mesh.vertices)} vertices, "
                             f"the store's {len(stored.local_points)}: the scene params changed since simulate")
        held[obj] = (mesh.vertices, mesh.faces)
    faces = {name: store.objects[name].faces for name in layout}
    rest = {name: store.objects[name].rest_positions for name in layout}
    return _assemble(layout, faces, rest, links, held, scene_cfg.table)


def scene_geometry(scene: Scene) -> EpisodeGeometry:
    """Render geometry of a live scene (closed-loop evaluation): x rows in `scene.objects` order, link_poses
    columns `scene.link_names`; held objects that are not also predicted are drawn from their pose column."""
    layout = scene.vertex_slices()
    held = {h.mesh.name: (h.mesh.vertices, h.mesh.faces) for h in scene.held.values() if h.mesh.name not in layout}
    return _assemble(layout, {n: m.faces for n, m in scene.objects.items()},
                     {n: m.vertices for n, m in scene.objects.items()}, scene.link_names, held, scene.table)


def _assemble(layout: dict[str, slice], faces: dict[str, np.ndarray], rest: dict[str, np.ndarray],
              links: Sequence[str], held: dict[str, tuple[np.ndarray, np.ndarray]],
              table: TableConfig) -> EpisodeGeometry:
    """Surfaces of the predicted objects (rows `layout`, rest shapes `rest`), robot link bodies and held
    objects (name -> body-frame (vertices, faces), posed by column held_<name> of `links`)."""
    links = list(links)
    surfaces = tuple(Surface(name, rows, np.asarray(faces[name], np.int32),
                             OBJECT_COLORS.get(name, DEFAULT_OBJECT_COLOR)) for name, rows in layout.items())
    bodies = [b for k, name in enumerate(links) if (b := _robot_body(name, k)) is not None]
    for obj, (vertices, tris) in held.items():
        column = f"{HELD_PREFIX}{obj}"
        bodies.append(Body(column, links.index(column), (),
                           (np.asarray(vertices, np.float32), np.asarray(tris, np.int32)),
                           OBJECT_COLORS.get(obj, DEFAULT_OBJECT_COLOR)))
    positions = np.concatenate([rest[n] for n in layout]).astype(np.float32)
    return EpisodeGeometry(surfaces, tuple(bodies), tuple(table.center_m), tuple(table.half_extents_m),
                           positions, tuple(links))
