"""New initial object states: rigid planar transforms (yaw about z through the centroid + xy shift) of a
settled source state, so the shape, the contacts with the table and the height stay as the simulator left them."""

from __future__ import annotations

import numpy as np

from wc.scene.config import TableConfig
from wc.tasks.base import InfeasibleEpisode


def planar_transform(x: np.ndarray, yaw_deg: float, shift_xy_m: tuple[float, float],
                     centre_xy_m: np.ndarray | None = None) -> np.ndarray:
    """Vertices x (N, 3) [m] yawed by yaw_deg about the vertical axis through centre_xy_m (default: their
    centroid), then moved by shift_xy_m; z is unchanged. float32 (N, 3)."""
    x = np.asarray(x, np.float64)
    yaw = np.deg2rad(yaw_deg)
    c, s = np.cos(yaw), np.sin(yaw)
    centre = x[:, :2].mean(axis=0) if centre_xy_m is None else np.asarray(centre_xy_m, np.float64)
    rel = x[:, :2] - centre
    out = x.copy()
    out[:, 0] = centre[0] + c * rel[:, 0] - s * rel[:, 1] + shift_xy_m[0]
    out[:, 1] = centre[1] + s * rel[:, 0] + c * rel[:, 1] + shift_xy_m[1]
    return out.astype(np.float32)


def check_on_table(x: np.ndarray, table: TableConfig) -> None:
    """InfeasibleEpisode unless every vertex of x (N, 3) lies over the table's sampled region (the part of the
    table top that carries environment samples, i.e. where the world model can feel the table)."""
    centre = np.asarray(table.sample_region_center_m, np.float64)
    half = np.asarray(table.sample_region_half_m, np.float64)
    outside = (np.abs(np.asarray(x, np.float64)[:, :2] - centre) > half).any(axis=1)
    if outside.any():
        raise InfeasibleEpisode(f"the transformed state leaves the table's sampled region ({int(outside.sum())} "
                                f"vertices beyond {centre.tolist()} +- {half.tolist()} m)")
