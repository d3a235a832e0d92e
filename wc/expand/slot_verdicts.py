"""The verdict of an episode a slot gave back (wc.expand.slot_rollout): the first failing frames of the one-frame
checks, kept on the device, completed on the host by the checks that look at several frames (adhesion, the camera
view) and the task's own verdict, in the order of wc.validate.predicates.PREDICATES, as `first_failure` orders them.
An episode stops at its first failing frame, so a check later in that order that would have failed on a later frame is
not reached; the verdict (rejected) is the same, the reason the first in order among those failed by then."""

from __future__ import annotations

import numpy as np

from wc.expand.frame_checks import FRAME_CHECKS, NEVER
from wc.scene.scene import Scene
from wc.tasks.base import EpisodeSpec, Task
from wc.validate.config import ValidateConfig
from wc.validate.predicates import PREDICATES, Episode


def slot_verdict(task: Task, scene: Scene, cfg: ValidateConfig, task_check: bool, spec: EpisodeSpec, ep: Episode,
                 first_frames: np.ndarray, complete: bool) -> tuple[str, int] | None:
    """(first failing check, frame) of an episode ep (its frames so far) whose one-frame checks first failed at
    first_frames (5,) (NEVER: passed); None when it passes. complete: the episode ran to its last frame (only then is
    the task's verdict asked)."""
    failed = {name: int(f) for name, f in zip(FRAME_CHECKS, first_frames) if f < NEVER}
    for name, predicate in PREDICATES.items():
        frame = failed.get(name) if name in FRAME_CHECKS else predicate(scene, ep, cfg)
        if frame is not None:
            return name, frame
    if not task_check or not complete:
        return None
    reason = task.check(scene, spec, ep.x, ep.action)
    return (reason, len(ep.x) - 1) if reason else None
