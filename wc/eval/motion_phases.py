"""Motion phases of an episode, read from its commanded actions (the store records no task-program phases).

Every frame is labelled by the commanded step into the next frame, in the order a manipulation goes:

    approach  before any gripper has closed (the arms move or wait)
    grasp     a gripper closes
    lift      after a grasp, the arms move (lift, carry, shake)
    hold      after a grasp, nothing moves
    release   a gripper opens
    drop      after a release (the bag falls, settles)

A phase is a run of frames of one label; the phases of an episode tile its frames [0, T).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wc.tasks.motion import ARM_COLUMNS
from wc.train.events import GRIPPER_COLUMNS, OPENING_EPS_M

PHASE_NAMES = ("approach", "grasp", "lift", "hold", "release", "drop")
JOINT_COLUMNS = [c for joints, _ in ARM_COLUMNS.values() for c in range(14)[joints]]  # arm joints in the action
JOINT_STILL_RAD = 1e-4  # a joint moving less than this per frame is still (IK of a held pose jitters below it)


@dataclass(frozen=True)
class MotionPhase:
    """Frames [start, stop) of one motion phase."""

    name: str
    start: int
    stop: int


def frame_labels(actions: np.ndarray) -> list[str]:
    """The phase name of every frame of actions (T, 14); the last frame keeps the label of the step into it."""
    a = np.asarray(actions, np.float64)
    if a.ndim != 2 or a.shape[1] != 14 or len(a) < 1:
        raise ValueError(f"actions must be (T >= 1, 14), got {a.shape}")
    grip = np.diff(a[:, GRIPPER_COLUMNS], axis=0)
    moving = (np.abs(np.diff(a[:, JOINT_COLUMNS], axis=0)) > JOINT_STILL_RAD).any(axis=1)
    labels, grasped, released = [], False, False
    for t in range(len(a) - 1):
        if (grip[t] < -OPENING_EPS_M).any():
            label, grasped = "grasp", True
        elif (grip[t] > OPENING_EPS_M).any():
            label, released = "release", True
        elif released:
            label = "drop"
        elif grasped:
            label = "lift" if moving[t] else "hold"
        else:
            label = "approach"
        labels.append(label)
    return labels + labels[-1:] if labels else ["approach"]


def motion_phases(actions: np.ndarray) -> list[MotionPhase]:
    """The runs of equal frame labels of actions (T, 14), in frame order; they tile [0, T)."""
    labels = frame_labels(actions)
    cuts = [0] + [t for t in range(1, len(labels)) if labels[t] != labels[t - 1]] + [len(labels)]
    return [MotionPhase(labels[a], a, b) for a, b in zip(cuts, cuts[1:])]


def phase_starts(phases: list[MotionPhase], start: int, stop: int, count: int) -> list[tuple[int, str]]:
    """Up to `count` (frame, phase name) rollout starts in frames [start, stop): the first frame of each phase that
    overlaps them (clipped to `start`) with at least one frame after it, spread evenly over those phases when there
    are more (count 1: the middle one)."""
    candidates = [(max(p.start, start), p.name) for p in phases if p.stop > start and p.start < stop - 1]
    candidates = [c for c in candidates if c[0] < stop - 1]
    if count <= 0 or not candidates:
        return []
    n = len(candidates)
    picked = sorted({int((k + 0.5) * n / count) for k in range(count)}) if n > count else range(n)
    return [candidates[i] for i in picked]
