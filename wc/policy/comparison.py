"""Whether the source-vs-expanded comparison compares anything.

The expanded dataset is the source episodes plus the generated ones the expand stage accepted. With none
accepted the two arms train on the same episodes, and their difference is noise. The dataset, finetune and
policy_eval reports carry the answer in one top-level flag, `FLAG`, and the success plot says it in its title.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

FLAG = "expanded_equals_source"  # the top-level report key
SUMMARY_FILE = "train_summary.json"  # a saved policy's training summary (wc.policy.finetune writes it)
WARNING = "the expanded dataset holds no generated episode: it equals the source one and the comparison compares nothing"


def expanded_equals_source(episodes: Mapping[str, int | None]) -> bool | None:
    """From the episode counts per arm: True when 'expanded' holds no more episodes than 'source' (it is source plus
    the generated ones); None when the two arms are not both present or a count is unknown."""
    source, expanded = episodes.get("source"), episodes.get("expanded")
    if source is None or expanded is None:
        return None
    return expanded <= source


def trained_episodes(model_dirs: Mapping[str, Path], summary_file: str) -> dict[str, int | None]:
    """Episodes each saved policy was trained on, from its training summary (None where it has none)."""
    counts: dict[str, int | None] = {}
    for name, path in model_dirs.items():
        summary = Path(path) / summary_file
        counts[name] = json.loads(summary.read_text()).get("episodes") if summary.is_file() else None
    return counts


def flagged_title(title: str, equal: bool | None) -> str:
    """A plot title that says when the arms trained on the same episodes."""
    return f"{title}\nNO GENERATED EPISODES: expanded = source" if equal else title
