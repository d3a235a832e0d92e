"""Work-unit streams run on an executor with their results filed in proposal order.

A stream is a planner in the driver: it proposes one unit at a time (`next_unit`) and files each unit's result
(`file`) in the order it proposed them, whatever order they finish in, and proposes again only after filing. So
what it proposes depends on the results filed before, never on timing or on the executor: with `in_flight` units
proposed ahead per stream, every executor sees the same units and the stream files the same results.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable, Iterator, Sequence
from typing import Any, Protocol

from wc.distributed.executors import FAILED, Executor, Unit


class Stream(Protocol):
    def next_unit(self) -> Unit | None:
        """The unit to run next; None: none is wanted now (asked again after the next result is filed)."""
        ...

    def file(self, result: Any) -> None:
        """The result of the oldest unit not yet filed."""
        ...


def drive(executor: Executor, streams: Sequence[Stream], in_flight: int = 1) -> Iterator[int]:
    """Run `streams` on `executor`, each with at most `in_flight` units proposed and not yet filed; yields each
    stream's index once it is finished (nothing in flight, nothing proposed), in stream order.

    A unit that kept failing (RayExecutor) ends its stream: its later units are cancelled unfiled. Once the
    executor is `stopping`, no stream proposes again; the units in flight finish and are filed."""
    if in_flight < 1:
        raise ValueError(f"in_flight must be >= 1, got {in_flight}")
    queues: list[deque[Hashable]] = [deque() for _ in streams]
    done: dict[Hashable, Any] = {}

    def top_up(i: int) -> None:
        while len(queues[i]) < in_flight and not executor.stopping:
            unit = streams[i].next_unit()
            if unit is None:
                return
            queues[i].append(executor.submit(unit))

    for i in range(len(streams)):
        top_up(i)
    first = 0
    while first < len(streams):
        if not queues[first]:
            yield first
            first += 1
            continue
        done.update(executor.wait())
        for i, queue in enumerate(queues):
            while queue and queue[0] in done:
                result = done.pop(queue.popleft())
                if result is FAILED:
                    executor.cancel(queue)
                    queue.clear()
                    break
                streams[i].file(result)
                top_up(i)
