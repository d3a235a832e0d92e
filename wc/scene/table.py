"""The table: a static box, and its environment sample set (points on the top surface near the workspace)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class TableSpec:
    """Axis-aligned box: center (3,) m in the world, half_extents (3,) m."""

    center: np.ndarray
    half_extents: np.ndarray

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, dtype=np.float64).reshape(3)
        self.half_extents = np.asarray(self.half_extents, dtype=np.float64).reshape(3)
        if not (np.isfinite(self.center).all() and np.isfinite(self.half_extents).all()
                and (self.half_extents > 0).all()):
            raise ValueError(f"TableSpec: need finite center and positive half_extents, got "
                             f"{self.center}, {self.half_extents}")

    @property
    def top_z(self) -> float:
        """World height of the table top, m."""
        return float(self.center[2] + self.half_extents[2])


def _axis_samples(lo: float, hi: float, spacing_m: float) -> np.ndarray:
    """Points spaced `spacing_m` apart, centred in [lo, hi] (one point if the interval is shorter)."""
    count = int(math.floor((hi - lo) / spacing_m + 1e-9)) + 1
    return 0.5 * (lo + hi) + spacing_m * (np.arange(count) - 0.5 * (count - 1))


def table_env_samples(spec: TableSpec, region_center_xy: np.ndarray, region_half_xy: np.ndarray,
                      spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Regular grid of points on the table top, only where the top overlaps the region.

    The region is an axis-aligned rectangle in world xy (region_center_xy ± region_half_xy, m): the
    part of the table the objects can reach, so the scene models no more table than it needs.
    Returns points (M, 3) float32 m in the table body's local frame (origin at `spec.center`, so the
    top is at z = half_extents[2]) and normals (M, 3) float32, all +z. Raises ValueError if the
    region misses the table top.
    """
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        raise ValueError(f"table_env_samples: spacing_m must be positive, got {spacing_m}")
    c, half = np.asarray(region_center_xy, dtype=np.float64), np.asarray(region_half_xy, dtype=np.float64)
    if c.shape != (2,) or half.shape != (2,) or not (half >= 0).all():
        raise ValueError(f"table_env_samples: region needs a center (2,) and non-negative half sizes (2,), "
                         f"got {c}, {half}")
    lo = np.maximum(c - half, spec.center[:2] - spec.half_extents[:2]) - spec.center[:2]
    hi = np.minimum(c + half, spec.center[:2] + spec.half_extents[:2]) - spec.center[:2]
    if (lo > hi).any():
        raise ValueError(f"table_env_samples: region {c} ± {half} does not overlap the table top "
                         f"{spec.center[:2]} ± {spec.half_extents[:2]}")
    gx, gy = np.meshgrid(_axis_samples(lo[0], hi[0], spacing_m), _axis_samples(lo[1], hi[1], spacing_m),
                         indexing="ij")
    points = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, spec.half_extents[2])], axis=1)
    normals = np.broadcast_to(np.array([0.0, 0.0, 1.0]), points.shape)
    return points.astype(np.float32), normals.astype(np.float32)
