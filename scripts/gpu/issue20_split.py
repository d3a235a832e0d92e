"""Split one validated store into the policy comparison's Newton data: the first SOURCE accepted episodes of TASK
(in episode order) -> OUT_SOURCE, the next EXTRA -> OUT_EXTRA (fresh Newton episodes for the newton_150 arm).

    python scripts/gpu/issue20_split.py STORE TASK SOURCE EXTRA OUT_SOURCE OUT_EXTRA
"""

from __future__ import annotations

import json
import sys

from wc.data.store import TrajectoryStore, copy_store


def main(store: str, task: str, n_source: int, n_extra: int, out_source: str, out_extra: str) -> None:
    src = TrajectoryStore(store)
    accepted = src.episodes_where(task=task, accepted=True)
    if len(accepted) < n_source + n_extra:
        print(f"WARNING {store}: {len(accepted)} accepted {task} episodes, fewer than {n_source} + {n_extra}",
              file=sys.stderr)
    source, extra = accepted[:n_source], accepted[n_source:n_source + n_extra]
    copy_store(src, out_source, source)
    copy_store(src, out_extra, extra)
    print(json.dumps({"accepted": len(accepted), "source": len(source), "extra": len(extra)}))


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0], a[1], int(a[2]), int(a[3]), a[4], a[5])
