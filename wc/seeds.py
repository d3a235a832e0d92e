"""Episode seeds in disjoint streams, so simulate, expand and policy evaluation never draw the same episode.

Stream k owns the integers [k * 2**32, (k + 1) * 2**32). A stage's episode seed is a uint32 SeedSequence
draw from (stage seed, task index, episode index) placed in its stream; policy evaluation's trial seeds
are `policy_eval.seed_offset + trial`, kept inside the policy stream by its config check. The simulate
stream is offset 0, so simulate's seeds are the plain draws they always were.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

STREAM_SPAN = 2**32  # seeds per stream: every uint32 draw fits


class SeedStream(IntEnum):
    SIMULATE = 0
    EXPAND = 1
    POLICY_EVAL = 2


def stream_range(stream: SeedStream) -> range:
    """The seeds stream `stream` may use."""
    return range(int(stream) * STREAM_SPAN, (int(stream) + 1) * STREAM_SPAN)


def episode_seed(stage_seed: int, task_index: int, episode_index: int,
                 stream: SeedStream = SeedStream.SIMULATE) -> int:
    """One independent seed per episode, derived from the stage seed, inside `stream`'s range."""
    draw = int(np.random.SeedSequence([stage_seed, task_index, episode_index]).generate_state(1)[0])
    return int(stream) * STREAM_SPAN + draw


def stream_of(seed: int) -> SeedStream:
    """The stream an episode seed belongs to; ValueError for a seed outside every stream."""
    index, _ = divmod(int(seed), STREAM_SPAN)
    if seed < 0 or index >= len(SeedStream):
        raise ValueError(f"episode seed {seed} lies outside every seed stream (0 .. {len(SeedStream) * STREAM_SPAN})")
    return SeedStream(index)
