"""The attrs a generated episode carries (its spec, parent, rigid move and verdict), whichever engine generated it;
the source store's scene goes into a generated store by wc.data.store.copy_scene."""

from __future__ import annotations

from typing import Any

from wc.expand.plan import PlannedEpisode, SourceEpisode


def episode_attrs(planned: PlannedEpisode, source: SourceEpisode, failure: str | None = None,
                  model_sha256: str | None = None) -> dict[str, Any]:
    """A generated episode's attrs: accepted when failure is None, else its first failing check; the SHA-256 of the
    weights that generated it."""
    s = planned.spec
    return {"task": s.task, "seed": s.seed, "cell": s.cell, "speed": s.speed, "amplitude": s.amplitude,
            "split": "train", "accepted": failure is None, "first_failure": failure, "source": "worldcontact",
            "parent": planned.parent, "yaw_deg": planned.yaw_deg, "shift_m": list(planned.shift_m),
            "model_sha256": model_sha256, **source.layout}
