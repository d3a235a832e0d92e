"""Take N episodes of a trajectory store into a new store: the first N in episode order, after skipping K, of
those that match a task and (by default) were accepted. Episode ids, attrs and the scene are kept.

    python -m wc.data.take STORE OUT -n N [--skip K] [--task TASK] [--include-rejected] [--at-most]

The policy comparison splits one Newton store this way into its 25 source episodes and the 125 fresh ones of its
Newton-150 control arm:

    python -m wc.data.take newton.zarr source.zarr -n 25 --task lift_handle
    python -m wc.data.take newton.zarr newton_extra.zarr -n 125 --skip 25 --task lift_handle

Fewer than N matching episodes after the skip is an error (exit 2) unless `--at-most` is given.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from wc.cli import run_cli
from wc.data.store import TrajectoryStore, copy_store


def matching_episodes(store: TrajectoryStore, task: str | None, accepted_only: bool) -> list[str]:
    """Ids of the episodes of `task` (every task when None), accepted ones only when `accepted_only`, in id order."""
    return store.episodes_where(task=task, accepted=True if accepted_only else None)


def take(store: str | Path, out: str | Path, n: int, *, skip: int = 0, task: str | None = None,
         accepted_only: bool = True, at_most: bool = False) -> dict[str, object]:
    """Copy episodes `skip` .. `skip + n` of the matching ones (`matching_episodes`) into a new store at `out`;
    returns what was taken. Raises ValueError when fewer than `n` remain after the skip (unless `at_most`) or none
    do, FileNotFoundError when `store` does not exist."""
    if n < 1 or skip < 0:
        raise ValueError(f"-n must be >= 1 and --skip >= 0 (got -n {n}, --skip {skip})")
    if not Path(store).exists():
        raise FileNotFoundError(f"{store}: no such store")
    src = TrajectoryStore(store)
    matching = matching_episodes(src, task, accepted_only)
    chosen = matching[skip:skip + n]
    what = f"{'accepted ' if accepted_only else ''}episodes{f' of {task}' if task else ''}"
    if not chosen or (len(chosen) < n and not at_most):
        hint = " (--at-most takes what there is)" if chosen else ""
        raise ValueError(f"{store}: {len(matching)} {what}, {len(chosen)} after skipping {skip}: fewer than the "
                         f"{n} asked for{hint}")
    copy_store(src, out, chosen)
    return {"store": str(store), "out": str(out), "matching": len(matching), "skipped": skip, "taken": len(chosen),
            "first": chosen[0], "last": chosen[-1]}


def main(argv: list[str] | None = None) -> dict[str, object]:
    parser = argparse.ArgumentParser(prog="python -m wc.data.take", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("store", type=Path, help="the store to take episodes from")
    parser.add_argument("out", type=Path, help="the new store (replaced if it is a store already)")
    parser.add_argument("-n", type=int, required=True, help="how many episodes to take")
    parser.add_argument("--skip", type=int, default=0, help="matching episodes to pass over first (default 0)")
    parser.add_argument("--task", default=None, help="only episodes of this task (default: every task)")
    parser.add_argument("--include-rejected", action="store_true", help="rejected episodes match too")
    parser.add_argument("--at-most", action="store_true", help="fewer than N matching episodes is not an error")
    args = parser.parse_args(argv)
    result = take(args.store, args.out, args.n, skip=args.skip, task=args.task,
                  accepted_only=not args.include_rejected, at_most=args.at_most)
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    run_cli(main, "take")
