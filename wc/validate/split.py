"""Deterministic train / val / test split of accepted episodes, per task.

Rule, for a task with n accepted episodes:
    test = min(test_per_task, n - 1)            # the test split is filled first,
    val  = min(val_per_task,  n - 1 - test)     # then val,
    train = n - test - val                      # and at least one episode always stays in train (n >= 1).
Which episodes land where: the task's episode ids, sorted, are shuffled by a generator seeded with
(split_seed, a stable hash of the task name); the first `test` go to test, the next `val` to val, the
rest to train. So the same episodes and seed give the same split, a task's split does not depend on
the other tasks, and a different seed reshuffles every task.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping

import numpy as np

SPLITS = ("train", "val", "test")


def split_counts(n: int, val_per_task: int, test_per_task: int) -> dict[str, int]:
    """Episodes per split for a task with n accepted episodes (the rule in the module docstring)."""
    if min(n, val_per_task, test_per_task) < 0:
        raise ValueError(f"counts must be >= 0, got n={n}, val_per_task={val_per_task}, test_per_task={test_per_task}")
    test = min(test_per_task, max(n - 1, 0))
    val = min(val_per_task, max(n - 1 - test, 0))
    return {"train": n - test - val, "val": val, "test": test}


def split_episodes(episode_tasks: Mapping[str, str], val_per_task: int, test_per_task: int,
                   seed: int) -> dict[str, str]:
    """Split of every episode: {episode id: "train" | "val" | "test"}, given {episode id: task}."""
    by_task: dict[str, list[str]] = {}
    for eid, task in episode_tasks.items():
        by_task.setdefault(task, []).append(eid)
    out: dict[str, str] = {}
    for task, ids in by_task.items():
        counts = split_counts(len(ids), val_per_task, test_per_task)
        rng = np.random.default_rng([seed, zlib.crc32(task.encode())])  # str hash() is salted per process
        ids = sorted(ids, key=lambda e: (len(e), e))  # the store's order, independent of the input's
        order = [ids[k] for k in rng.permutation(len(ids))]
        labels = ["test"] * counts["test"] + ["val"] * counts["val"] + ["train"] * counts["train"]
        out.update(zip(order, labels))
    return out
