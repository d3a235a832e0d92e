"""PiPER collision primitives per link and surface sample sets (points + outward normals, link frames).

Shapes are ours to choose (piper.md gives only the chain): one box per link, sized to the link
offsets of the chain, and the finger pads as the 0.04 x 0.06 x 0.01 m boxes of piper.py.
Link frames are those of wc.scene.piper (the child frame of each joint).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from wc.rotations import quat_matrices
from wc.scene.piper import CHAIN, LINK_NAMES, PAD_CENTRE_IN_FINGER_M, PAD_HALF_EXTENTS_M

ARM_HALF_WIDTH_M = 0.035  # upper arm
FOREARM_HALF_WIDTH_M = 0.03  # forearm, wrist
GRIPPER_HALF_EXTENTS_M = (0.035, 0.055, 0.065)  # gripper body: x, y (finger travel axis), z (approach)


@dataclass(frozen=True)
class LinkShape:
    """A primitive fixed to a link. size: box half extents (hx, hy, hz) in m, or capsule (radius, half_height)
    with the capsule axis along its local z (Newton's add_shape_box / add_shape_capsule arguments)."""

    link: str
    kind: Literal["box", "capsule"]
    local_pos: tuple[float, float, float]
    local_quat_xyzw: tuple[float, float, float, float]
    size: tuple[float, ...]


def _z_rotation(angle: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(0.5 * angle), math.cos(0.5 * angle))


def _segment_box(link: str, end: Sequence[float], half_width: float) -> LinkShape:
    """Box from the link origin to `end` (in the link's xy plane), padded by half_width around both joints."""
    length = math.hypot(end[0], end[1])
    centre = (0.5 * end[0], 0.5 * end[1], 0.0)
    half = (0.5 * length + half_width, half_width, half_width)
    return LinkShape(link, "box", centre, _z_rotation(math.atan2(end[1], end[0])), half)


def piper_link_shapes() -> list[LinkShape]:
    """Collision primitives of the 8 moving bodies of one arm, in link frames."""
    origin = {j.child: j.origin_pos for j in CHAIN}
    ident = (0.0, 0.0, 0.0, 1.0)
    w, g = FOREARM_HALF_WIDTH_M, GRIPPER_HALF_EXTENTS_M
    base_h = origin["link1"][2]  # link1 sits base_h above base_link; its box also covers the base column
    top = ARM_HALF_WIDTH_M  # up to the top of the shoulder joint
    wrist_lo, wrist_hi = -w, origin["link6"][1] - 0.005  # link5 along +y, stopping short of the flange
    return [
        LinkShape("link1", "box", (0.0, 0.0, 0.5 * (top - base_h)), ident, (0.045, 0.045, 0.5 * (top + base_h))),
        _segment_box("link2", origin["link3"], ARM_HALF_WIDTH_M),  # shoulder -> elbow
        _segment_box("link3", origin["link4"], w),  # elbow -> wrist
        LinkShape("link4", "box", (0.0, 0.0, 0.0), ident, (w, w, w)),  # wrist housing (joints 4 and 5 share it)
        LinkShape("link5", "box", (0.0, 0.5 * (wrist_lo + wrist_hi), 0.0), ident, (w, 0.5 * (wrist_hi - wrist_lo), w)),
        LinkShape("link6", "box", (0.0, 0.0, g[2]), ident, g),  # flange + gripper body up to the finger rail
        LinkShape("finger_a", "box", PAD_CENTRE_IN_FINGER_M["finger_a"], ident, PAD_HALF_EXTENTS_M),
        LinkShape("finger_b", "box", PAD_CENTRE_IN_FINGER_M["finger_b"], ident, PAD_HALF_EXTENTS_M),
    ]


def _box_samples(half: Sequence[float], spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Cell-centred grid on each of the 6 faces (at least one point per face), in the box frame."""
    points, normals = [], []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        nu, nv = (max(1, math.ceil(2 * half[a] / spacing)) for a in (u, v))
        gu = (np.arange(nu) + 0.5) / nu * 2 * half[u] - half[u]
        gv = (np.arange(nv) + 0.5) / nv * 2 * half[v] - half[v]
        uu, vv = np.meshgrid(gu, gv, indexing="ij")
        for sign in (-1.0, 1.0):
            p = np.zeros((uu.size, 3))
            p[:, u], p[:, v], p[:, axis] = uu.ravel(), vv.ravel(), sign * half[axis]
            n = np.zeros_like(p)
            n[:, axis] = sign
            points.append(p)
            normals.append(n)
    return np.concatenate(points), np.concatenate(normals)


def _capsule_samples(radius: float, half_height: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Rings on the cylinder and Fibonacci points on the two hemispheres, in the capsule frame (axis z)."""
    n_around = max(3, math.ceil(2 * math.pi * radius / spacing))
    n_len = max(1, math.ceil(2 * half_height / spacing))
    phi = (np.arange(n_around) + 0.5) / n_around * 2 * math.pi
    z = (np.arange(n_len) + 0.5) / n_len * 2 * half_height - half_height
    pp, zz = np.meshgrid(phi, z, indexing="ij")
    ring = np.stack((np.cos(pp.ravel()), np.sin(pp.ravel()), np.zeros(pp.size)), axis=1)
    points, normals = [radius * ring + np.outer(zz.ravel(), [0, 0, 1])], [ring]
    n_cap = max(1, math.ceil(2 * math.pi * radius**2 / spacing**2))
    k = np.arange(n_cap) + 0.5
    cos_t = 1.0 - k / n_cap  # uniform in area over the hemisphere z >= 0
    sin_t = np.sqrt(1.0 - cos_t**2)
    ang = math.pi * (1 + 5**0.5) * k
    cap = np.stack((sin_t * np.cos(ang), sin_t * np.sin(ang), cos_t), axis=1)
    for sign in (-1.0, 1.0):
        n = cap * np.array([1.0, 1.0, sign])
        points.append(radius * n + [0.0, 0.0, sign * half_height])
        normals.append(n)
    return np.concatenate(points), np.concatenate(normals)


def shape_surface_samples(shape: LinkShape, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) and outward unit normals (M, 3), float32, on one primitive's surface, in its link frame."""
    if shape.kind == "box":
        p, n = _box_samples(shape.size, spacing_m)
    elif shape.kind == "capsule":
        p, n = _capsule_samples(*shape.size, spacing_m)
    else:
        raise ValueError(f"unknown shape kind {shape.kind!r}, expected 'box' or 'capsule'")
    rot = quat_matrices(np.asarray(shape.local_quat_xyzw, dtype=np.float64))
    return (p @ rot.T + shape.local_pos).astype(np.float32), (n @ rot.T).astype(np.float32)


def link_surface_samples(
    spacing_m: float, links: Sequence[str], shapes: Sequence[LinkShape] | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per requested link: surface points (M, 3) and outward unit normals (M, 3), float32, in the link frame.

    Roughly uniform with the given spacing (m) on every primitive of the link, at least one point per face.
    shapes defaults to piper_link_shapes() (one primitive per link, so no sample hides inside another).
    """
    if spacing_m <= 0:
        raise ValueError(f"spacing_m must be positive, got {spacing_m}")
    unknown = [name for name in links if name not in LINK_NAMES]
    if unknown:
        raise ValueError(f"unknown links {unknown}, expected names from {LINK_NAMES}")
    shapes = piper_link_shapes() if shapes is None else shapes
    out = {}
    for name in links:
        samples = [shape_surface_samples(s, spacing_m) for s in shapes if s.link == name]
        out[name] = (np.concatenate([p for p, _ in samples]), np.concatenate([n for _, n in samples]))
    return out
