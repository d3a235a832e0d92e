"""Work-unit workers that fail on purpose, for the ray executor's fault tests. Ray worker processes import them by
name (the tests run from the repository root, which Ray puts on its workers' path), so they keep no state in memory:
a unit that fails only once leaves a marker file behind in `folder`."""

from __future__ import annotations

import os
from pathlib import Path

from wc.render.worker import RenderBatch, RenderWorker

BAD_EPISODE = "ep_000001"  # the episode FailingRenderWorker cannot render


def flaky_doubler(folder: str, mode: str, bad: int):
    """A worker doubling its payload, except on payload `bad`: mode 'raise_once' raises the first time, 'die_once'
    kills its process the first time, 'always' raises every time."""

    def double(payload: int) -> int:
        marker = Path(folder) / f"{mode}-{payload}"  # one byte per failed try
        if payload == bad and (mode == "always" or not marker.exists()):
            with marker.open("a") as f:
                f.write("x")
            if mode == "die_once":
                os._exit(1)
            raise RuntimeError(f"injected failure on unit {payload}")
        return 2 * payload

    return double


class FailingRenderWorker(RenderWorker):
    """A render worker that raises on every unit holding BAD_EPISODE."""

    def __call__(self, payload: tuple[str, list[str]]) -> RenderBatch:
        if BAD_EPISODE in payload[1]:
            raise RuntimeError(f"injected failure rendering {BAD_EPISODE}")
        return super().__call__(payload)
