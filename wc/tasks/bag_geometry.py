"""Where things are on the bag: initial placements and grasp points read off a (settled) state.

Everything is computed from the vertex positions and the mesh's groups / attributes (see
wc/scene/bag.py), so it works for any resolution and any settled shape.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from wc.scene.mesh import ObjectMesh
from wc.scene.scene import Scene
from wc.tasks.motion import arm_base, facing, radial


def placed(vertices: np.ndarray, yaw_deg: float, roll_deg: float, centre_xy: np.ndarray, bottom_z: float
           ) -> np.ndarray:
    """Rest vertices rolled about x (90 = lying on the front face), yawed about z, then moved so the
    bounding box is centred at centre_xy with its lowest point at bottom_z."""
    r = Rotation.from_euler("zx", [yaw_deg, roll_deg], degrees=True)
    x = r.apply(np.asarray(vertices, np.float64))
    lo, hi = x.min(0), x.max(0)
    return (x + np.array([*(np.asarray(centre_xy) - 0.5 * (lo[:2] + hi[:2])), bottom_z - lo[2]])).astype(np.float32)


def bag_rows(scene: Scene, x: np.ndarray) -> np.ndarray:
    return x[scene.vertex_slices()["bag"]]


def handle_of(scene: Scene, xb: np.ndarray, side: str) -> str:
    """The handle group nearer an arm's base."""
    bag = scene.objects["bag"]
    centroid = {g: xb[bag.groups[g]].mean(0) for g in ("handle_0", "handle_1")}
    return min(centroid, key=lambda g: np.linalg.norm(centroid[g][:2] - arm_base(scene, side)[:2]))


def handle_grasp(scene: Scene, x: np.ndarray, side: str, depth_m: float, across: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grasp point (3,), pad separation axis (3,) and horizontal direction away from the arm's base
    (3,) for pinching the handle nearer `side`'s arm in state x.

    The pads straddle the strap's two legs `depth_m` below its apex, at `across` (0 inner edge ..
    1 outer edge) of the strap's width, and squeeze the legs together: the pad separation axis is
    the strap's horizontal front-to-back direction, centred between the legs as they lie.
    """
    bag: ObjectMesh = scene.objects["bag"]
    xb = bag_rows(scene, x)
    idx = bag.groups[handle_of(scene, xb, side)]
    u, s = bag.attributes["handle_u"][idx], bag.attributes["handle_s"][idx]
    band = idx[np.abs(u - across) <= np.abs(u - across).min() + 1e-6]
    apex = xb[band[np.argmax(xb[band, 2])]]
    point = apex - np.array([0.0, 0.0, depth_m])
    sep = xb[idx[s < 0.5]].mean(0) - xb[idx[s > 0.5]].mean(0)
    sep[2] = 0.0
    y = facing(sep / np.linalg.norm(sep) if np.linalg.norm(sep) > 1e-6 else np.array([0.0, 1.0, 0.0]), scene, side)
    legs = xb[idx[(xb[idx, 2] <= point[2] + 0.5 * depth_m) & (xb[idx, 2] >= point[2] - depth_m)]]
    if len(legs):  # a settled strap may lean: centre the pads between its legs
        spread = (legs - point) @ y
        point = point + 0.5 * (spread.min() + spread.max()) * y
    return point, y, radial(scene, side, point)


def width_axes(scene: Scene, xb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre (3,), horizontal width axis (3,) and front normal (3,) (the front wall's outward side,
    towards -y in the rest pose) of the bag's rim as it lies now."""
    bag = scene.objects["bag"]
    rim = xb[bag.groups["rim"]]
    centre = rim.mean(0)
    front = xb[bag.groups["rim"][bag.vertices[bag.groups["rim"], 1] < 0]].mean(0) - centre
    front[2] = 0.0
    front /= max(np.linalg.norm(front), 1e-9)
    width = np.cross(np.array([0.0, 0.0, 1.0]), front)
    return centre, width, front


def rim_grasp(scene: Scene, x: np.ndarray, side: str, along: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grasp point, pad separation axis and away direction for pinching the front wall's top edge at
    `along` (-1 .. 1 of the half-width between the handles) with `side`'s gripper."""
    bag = scene.objects["bag"]
    xb = bag_rows(scene, x)
    centre, width, front = width_axes(scene, xb)
    rim = bag.groups["rim"]
    wall = rim[(bag.attributes["part"][rim] == 0) & (bag.vertices[rim, 1] < 0)]
    half = np.abs((xb[wall] - centre) @ width).max()
    target = centre + along * half * width
    k = wall[np.argmin(np.linalg.norm(xb[wall] - target, axis=1))]
    return xb[k].astype(np.float64), facing(front, scene, side), radial(scene, side, xb[k])


def top_surface_point(scene: Scene, x: np.ndarray, offset_xy: np.ndarray, radius_m: float = 0.02) -> np.ndarray:
    """The highest bag point within radius_m (horizontally) of the bag's centre + offset_xy."""
    xb = bag_rows(scene, x)
    target = xb.mean(0)[:2] + np.asarray(offset_xy)
    near = np.linalg.norm(xb[:, :2] - target, axis=1) <= radius_m
    z = xb[near, 2].max() if near.any() else xb[:, 2].max()
    return np.array([target[0], target[1], z])


def bag_bottom_centre(scene: Scene, x: np.ndarray) -> np.ndarray:
    """Mean position of the bag's bottom panel."""
    return bag_rows(scene, x)[scene.objects["bag"].groups["bottom"]].mean(0)


def ends_above(scene: Scene, x: np.ndarray, height_m: float, failure: str, names: tuple[str, ...] = ("bag",)
               ) -> str | None:
    """None if every named object's lowest vertex ends height_m above the table, else `failure`."""
    return None if min(lowest_height(scene, x[-1:], n)[0] for n in names) >= height_m else failure


def lowest_height(scene: Scene, x: np.ndarray, name: str = "bag") -> np.ndarray:
    """Height of an object's lowest vertex above the table top, per frame: x (T, N, 3) -> (T,)."""
    return x[:, scene.vertex_slices()[name], 2].min(axis=1) - scene.table.top_z
