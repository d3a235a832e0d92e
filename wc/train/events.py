"""Contact events in the training data, and the sampling weights that oversample the windows around them.

The frames where contact changes (the pads closing or opening, the cloth hitting the table or a body) are a
small share of the windows, yet they decide whether a long rollout keeps its grasp. A frame is an event when a
gripper's commanded opening moves, or when some predicted vertex's acceleration |v_k - v_{k-1}| / dt exceeds
`train.event_accel_m_s2` (an impact). A training window within `train.event_margin_frames` of an event is drawn
`1 + train.event_oversample` times as often as one that is not (0: uniform sampling, the paper's).
"""

from __future__ import annotations

import numpy as np

from wc.data.store import TrajectoryStore
from wc.tasks.motion import ARM_COLUMNS
from wc.train.data import Phase, Window, read_phase_window

GRIPPER_COLUMNS = [opening for _, opening in ARM_COLUMNS.values()]  # commanded finger opening per arm
OPENING_EPS_M = 1e-5  # a smaller change of a commanded opening between frames is numerical noise


def event_frames(action: np.ndarray, v: np.ndarray, dt: float, accel_m_s2: float) -> np.ndarray:
    """(T,) bool: frames where a gripper opening changed since the last frame or a vertex accelerated beyond
    `accel_m_s2`. action (T, 14), v (T, N, 3) m/s."""
    events = np.zeros(len(action), dtype=bool)
    gripping = np.abs(np.diff(action[:, GRIPPER_COLUMNS], axis=0)).max(axis=1) > OPENING_EPS_M
    accel = np.linalg.norm(np.diff(v, axis=0), axis=-1).max(axis=1) / dt if v.shape[1] else np.zeros(len(v) - 1)
    events[1:] = gripping | (accel > accel_m_s2)
    return events


def window_weights(store: TrajectoryStore, phases: list[Phase], windows: list[Window], length: int,
                   oversample: float, margin_frames: int, accel_m_s2: float) -> tuple[np.ndarray | None, float]:
    """(per-window sampling weights, or None for uniform; share of windows near an event)."""
    if oversample <= 0:
        return None, float("nan")
    near: dict[Phase, np.ndarray] = {}
    for p in phases:
        a = read_phase_window(store, p, p.start, p.stop - p.start)
        events = np.flatnonzero(event_frames(a["action"], a["v"], store.dt, accel_m_s2)) + p.start
        marked = np.zeros(p.stop + length + margin_frames, dtype=bool)
        for e in events:
            marked[max(p.start, e - margin_frames):e + margin_frames + 1] = True
        near[p] = marked
    hits = np.array([near[w.phase][w.start:w.start + length].any() for w in windows])
    return np.where(hits, 1.0 + oversample, 1.0), float(hits.mean()) if len(hits) else float("nan")
