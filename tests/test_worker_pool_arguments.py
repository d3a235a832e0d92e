"""wc.worker_pool.spawn_pool hands its initializer's arguments to the spawned workers through a temporary file (more
than a pipe's buffer written to a child would hold the parent until that child had imported its modules), and the file
goes with the pool."""

from __future__ import annotations

import os

from wc.worker_pool import spawn_pool

_SEEN: bytes = b""


def _remember(value: bytes) -> None:
    global _SEEN
    _SEEN = value


def _seen() -> tuple[int, int]:
    return len(_SEEN), _SEEN.count(b"x")


def test_large_initializer_arguments_reach_every_worker_and_their_file_goes_with_the_pool():
    big = b"x" * (1 << 20)  # 1 MiB: 16 times a Linux pipe's buffer
    pool = spawn_pool(2, _remember, (big,))
    path = pool.initargs_file
    try:
        assert os.path.exists(path)
        results = [f.result(timeout=300) for f in [pool.submit(_seen) for _ in range(4)]]
        assert results == [(len(big), len(big))] * 4
    finally:
        pool.shutdown()
    assert not os.path.exists(path)
