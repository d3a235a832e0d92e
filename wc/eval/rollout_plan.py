"""Which held-out rollouts evaluate makes: per held-out span (a layout phase of a test episode, or a held-out block
of training's validation data), one from its first frame to its end (the whole episode, capped at `episode_frames`
steps) and up to `starts_per_span` shorter ones (`rollout_frames` steps) from the first frames of the motion phases
in it (wc.eval.motion_phases: approach, grasp, lift, hold, release, drop), spread over them. The speed-accuracy
chart times `rollout_frames` steps from a charted span's first frame: its whole rollout where that is no longer, else a
rollout of its own (label CHART, on the chart only), so that the Newton methods never simulate whole episodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wc.data.store import TrajectoryStore
from wc.eval.motion_phases import motion_phases, phase_starts
from wc.train.data import Phase

EPISODE = "episode"  # the label of a span's whole rollout
CHART = "chart"  # the label of a chart-only rollout


@dataclass(frozen=True)
class HeldOutRollout:
    """`frames` frames (steps + 1) of `span` from frame `start`; `label`: EPISODE for the span's whole rollout, else
    the motion phase of its start frame."""

    span: Phase
    start: int
    frames: int
    label: str

    @property
    def whole(self) -> bool:
        return self.label == EPISODE

    def charted(self, chart: set[Phase], rollout_frames: int) -> bool:
        """Whether it is timed on the chart of spans `chart`."""
        return self.span in chart and (self.label == CHART or self.whole and self.frames <= rollout_frames + 1)


def plan_rollouts(store: TrajectoryStore, spans: list[Phase], rollout_frames: int, episode_frames: int,
                  starts_per_span: int, chart: set[Phase] = frozenset()) -> list[HeldOutRollout]:
    """The held-out rollouts of `spans` (spans shorter than 2 frames have none), span by span: its whole rollout, its
    chart rollout (a span in `chart` whose whole rollout is longer than rollout_frames), then its motion-phase starts
    in frame order. Motion phases are read from the whole episode's actions, so a block in the middle of an episode
    knows whether a grasp came before it."""
    actions: dict[str, np.ndarray] = {}
    out = []
    for span in spans:
        if span.stop - span.start < 2:
            continue
        whole = HeldOutRollout(span, span.start, min(episode_frames + 1, span.stop - span.start), EPISODE)
        out.append(whole)
        if span in chart and not whole.charted(chart, rollout_frames):
            out.append(HeldOutRollout(span, span.start, min(rollout_frames + 1, whole.frames), CHART))
        if span.episode not in actions:
            actions[span.episode] = store.read_episode(span.episode, ["action"])["action"]
        for frame, name in phase_starts(motion_phases(actions[span.episode]), span.start, span.stop, starts_per_span):
            out.append(HeldOutRollout(span, frame, min(rollout_frames + 1, span.stop - frame), name))
    return out
