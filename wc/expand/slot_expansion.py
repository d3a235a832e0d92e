"""The expand stage's host loop on the slot engine (`expand.engine: slots`): proposals, planning, slots, verdicts,
writing, with the device never waiting for the host where it can be avoided.

- Proposals: the coverage planner proposes episode i from the verdicts of the episodes filed before it; at most
  `plans_ahead` episodes are proposed and not yet filed, and verdicts are filed in proposal order, so the episodes
  depend on the params and the seed alone (not on timing).
- Planning runs in a pool (wc.expand.plan_pool) while the device rolls out the slots (wc.expand.slot_rollout).
- Every `sync_every` frames the host reads the slots' first failures (one sync); a slot whose episode ended or failed
  gives its trajectory back and takes the next planned episode; the episode's verdict is completed on the host
  (wc.expand.slot_verdicts) while the device runs the next frames, and filed in order; accepted episodes are written
  by a writer thread.
- In the tail (nothing left to load) the running episodes move where they stand to half as many slots while they fill
  at most half (`slots.tail_min_slots`) and their frames left outweigh a capture: a frame costs the same whether its
  slots are busy or not (not when compiling: a new slot count would compile again). A plan longer than the slots
  hold moves them to longer slots the same way.
- Wall time per phase (planning, device wait, verdicts, loading, I/O) and device time per part of a frame
  (network, projection, untangle, checks) go into the report.
"""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from wc.agent.planner import CoveragePlanner
from wc.expand.config import ExpandConfig
from wc.expand.frame_checks import NEVER
from wc.expand.phase_timer import PhaseTimer
from wc.expand.plan import PlannedEpisode, SourceEpisode, pick_parent, plan_seed
from wc.expand.plan_pool import PlanPool, PlanResult
from wc.expand.slot_rollout import PARTS, SlotPlan, SlotRollout
from wc.expand.slot_verdicts import slot_verdict
from wc.scene.scene import Scene
from wc.tasks.base import UNREACHABLE, EpisodeSpec, Task
from wc.validate.config import ValidateConfig
from wc.validate.failure_detail import failure_detail
from wc.validate.predicates import PREDICATES, Episode


@dataclass
class _Proposed:
    index: int
    spec: EpisodeSpec
    source: SourceEpisode
    plan: Future[PlanResult]


@dataclass
class _Running:
    index: int
    spec: EpisodeSpec
    source: SourceEpisode
    planned: PlannedEpisode
    poses: np.ndarray  # (T, P, 7)

    def slot_plan(self) -> SlotPlan:
        return SlotPlan(self.planned.x0, self.poses)


@dataclass
class _Outcome:
    """A filed-to-be result: infeasible (reason) or rolled out (trajectory and verdict)."""

    proposed: _Proposed | _Running
    infeasible: str | None = None
    x: np.ndarray | None = None
    v: np.ndarray | None = None
    failure: tuple[str, int] | None = None
    detail: dict[str, Any] | None = None
    first: np.ndarray | None = None  # a rolled-out episode's first failing frames (FRAME_CHECKS); None once judged
    complete: bool = False  # ... it ran to its last planned frame


FRAMES_MARGIN = 1.5  # slot buffers hold this times the longest episode planned so far
MIN_EXPECTED_ACCEPTANCE = 0.25  # proposals ahead of the target at most 1 / this times the episodes still wanted


class SlotExpansion:
    """One task's expansion on `cfg.batch_size` slots (module docstring). make_rollout(frames, batch): the SlotRollout
    of `batch` slots that hold episodes of up to `frames` frames; write(accepted, running, x, v, failure): stores a
    filed episode (on the writer thread); wanted: accepted generated episodes to reach; started: time.perf_counter()
    of the stage; shard: whose plan seeds (wc.expand.plan.plan_seed)."""

    def __init__(self, task: Task, scene: Scene, sources: list[SourceEpisode], cfg: ExpandConfig,
                 validate_cfg: ValidateConfig, dt: float, wanted: int, make_rollout: Callable[..., SlotRollout],
                 pool: PlanPool, started: float, write: Callable[..., None],
                 on_filed: Callable[[SlotExpansion], None] | None = None, shard: int = 0) -> None:
        self.task, self.scene, self.sources, self.cfg, self.validate_cfg = task, scene, sources, cfg, validate_cfg
        self.dt, self.wanted, self.make_rollout, self.pool, self.started = dt, wanted, make_rollout, pool, started
        self.write, self.on_filed, self.shard = write, on_filed, shard
        self.rollout: SlotRollout | None = None
        self.planner = CoveragePlanner()
        self.ahead = cfg.slots.plans_ahead or 2 * cfg.batch_size
        self.proposed = self.filed = self.accepted = self.generated = self.frames = 0
        self.surplus = 0  # episodes filed after the target was reached: neither counted nor written
        self.queue: deque[_Proposed] = deque()
        self.slots: list[_Running | None] = [None] * cfg.batch_size
        self.outcomes: dict[int, _Outcome] = {}
        self.rejections: dict[str, int] = {name: 0 for name in PREDICATES}
        self.rejected: list[dict[str, Any]] = []
        self.infeasible: list[dict[str, Any]] = []
        self.timer = PhaseTimer()
        self.restarts = 0  # slots made again: for a longer plan (episodes moved over) or a neighbour overflow (restarted)
        self.shrinks = 0  # moves of the tail's episodes to fewer slots
        self._retired_part_s = dict.fromkeys(PARTS, 0.0)  # device time of rollouts replaced (restarts, shrinks)
        self.capture_s = 0.0  # wall time of the last rebuild's capture
        self.loads = 0  # planned episodes loaded into a slot (restarts not counted)
        self.io = ThreadPoolExecutor(1)
        self._writes: list[Future[None]] = []

    # -- proposals and planning --
    def _may_propose(self) -> bool:
        """While the episodes in flight, at the acceptance rate filed so far (before any: slots.expected_acceptance),
        are not expected to reach the target (so the last slots fill with enough episodes to cover its rejections
        instead of waiting for them one wave at a time), within max_attempts, plans_ahead and max_minutes."""
        cfg = self.cfg
        in_flight = self.proposed - self.filed
        rate = (max(self.accepted / self.generated, MIN_EXPECTED_ACCEPTANCE) if self.generated
                else cfg.slots.expected_acceptance)
        return (self.accepted + rate * in_flight < self.wanted and self.proposed < cfg.max_attempts
                and in_flight < self.ahead
                and not (cfg.max_minutes > 0 and time.perf_counter() - self.started > 60.0 * cfg.max_minutes))

    def _propose(self) -> None:
        with self.timer.phase("planning"):
            while self._may_propose():
                i = self.proposed
                spec = self.planner.propose(self.task, plan_seed(self.cfg.seed, self.shard, i))
                source = pick_parent(self.sources, spec.cell, i)
                self.queue.append(_Proposed(i, spec, source, self.pool.submit(spec, self.sources.index(source))))
                self.proposed += 1

    def _fill(self) -> None:
        """Free slots take planned episodes (infeasible plans become outcomes); waits for a plan only when every
        slot is free."""
        free = [s for s, r in enumerate(self.slots) if r is None]
        taken: list[tuple[int, _Running]] = []
        with self.timer.phase("planning"):
            while free and self.queue:
                head = self.queue[0]
                if not head.plan.done() and (taken or any(r is not None for r in self.slots)):
                    break
                self.queue.popleft()
                result = head.plan.result()
                if result.planned is None:
                    self.outcomes[head.index] = _Outcome(head, infeasible=result.infeasible)
                    continue
                taken.append((free.pop(0), _Running(head.index, head.spec, head.source, result.planned, result.poses)))
        if not taken:
            return
        self.loads += len(taken)
        longest = max(len(r.poses) for _, r in taken)
        if self.rollout is None or longest > self.rollout.frames:  # the running episodes move over where they stand
            self.restarts += self.rollout is not None
            self._rebuild(int(np.ceil(longest * FRAMES_MARGIN)), len(self.slots), taken[0][1].slot_plan())
            free = [s for s, r in enumerate(self.slots) if r is None]
            taken = [(free[k], r) for k, (_, r) in enumerate(taken)]
        for s, running in taken:
            self.slots[s] = running
        with self.timer.phase("loading"):
            self.rollout.load([s for s, _ in taken], [r.slot_plan() for _, r in taken])

    # -- verdicts and filing --
    def _retire(self, t: np.ndarray, first: np.ndarray) -> None:
        """Slots whose episode ended or failed give their trajectories back (judged later, `_judge`) and are free."""
        done = [s for s, r in enumerate(self.slots)
                if r is not None and (t[s] >= len(r.poses) - 1 or (first[s] < NEVER).any())]
        if not done:
            return
        with self.timer.phase("reading"):
            trajectories = self.rollout.take(done, [int(t[s]) for s in done])
        for s, (x, v) in zip(done, trajectories):
            r = self.slots[s]
            self.outcomes[r.index] = _Outcome(r, x=x, v=v, first=first[s].copy(), complete=len(x) == len(r.poses))
            self.slots[s] = None

    def _judge(self, out: _Outcome) -> None:
        """A rolled-out episode's verdict and its failure's detail, completed on the host (wc.expand.slot_verdicts)."""
        with self.timer.phase("verdicts"):
            r, n = out.proposed, len(out.x)
            ep = Episode(out.x, out.v, r.planned.actions[:n], r.poses[:n, :len(self.scene.link_names)], self.dt)
            out.failure = slot_verdict(self.task, self.scene, self.validate_cfg, self.cfg.task_check, r.spec, ep,
                                       out.first, complete=out.complete)
            out.detail = failure_detail(self.scene, ep, self.validate_cfg, *out.failure) if out.failure else {}
            out.first = None

    def _file(self, judge: bool = True) -> None:
        """File the outcomes in proposal order, judging rolled-out episodes first (judge False: stop at the first one
        not judged yet, so that the host does not judge while the device waits); once the target is reached, later
        ones are surplus (neither judged nor written)."""
        while self.filed in self.outcomes:
            out = self.outcomes[self.filed]
            if self.done:
                del self.outcomes[self.filed]
                self.filed += 1
                self.surplus += 1
                continue
            if out.first is not None:
                if not judge:
                    return
                self._judge(out)
            del self.outcomes[self.filed]
            p = out.proposed
            self.filed += 1
            if out.infeasible is not None:
                self.planner.record(p.spec, UNREACHABLE)
                self.infeasible.append({"seed": p.spec.seed, "cell": p.spec.cell, "parent": p.source.eid,
                                        "reason": out.infeasible})
                continue
            self.planner.record(p.spec, *(out.failure or (None, None)))
            self.generated += 1
            self.frames += len(out.x)
            if out.failure is None:
                self.accepted += 1
            else:
                name, frame = out.failure
                self.rejections[name] = self.rejections.get(name, 0) + 1
                self.rejected.append({"seed": p.spec.seed, "cell": p.spec.cell, "parent": p.planned.parent,
                                      "reason": name, "frame": frame, "frames": len(out.x), **out.detail})
            self._writes.append(self.io.submit(self.write, out.failure is None, p, out.x, out.v, out.failure))
            if self.on_filed is not None:
                self.on_filed(self)

    # -- the loop --
    def _rebuild(self, frames: int, size: int, park: SlotPlan) -> None:
        """New slots (`size` of up to `frames` frames, the current neighbour capacities), their graphs captured on
        slots parked on park's frame 0; the running episodes move to the first slots where they stand."""
        previous = self.rollout
        running = [s for s, r in enumerate(self.slots) if r is not None]
        started = time.perf_counter()
        with self.timer.phase("capture"):
            self.rollout = self.make_rollout(frames, size)
            if previous is not None:
                self.rollout.grow_capacities([], previous.capacities)
            self._capture(park)
            if running:
                self.rollout.adopt(previous, running)
        self.capture_s = time.perf_counter() - started
        if previous is not None:
            for k, v in previous.part_s.items():  # its frames' events were read at the last sync
                self._retired_part_s[k] += v
        self.slots = [self.slots[s] for s in running] + [None] * (size - len(running))

    def _shrink_tail(self) -> None:
        """Nothing left to load (queue empty, no proposal due): the running episodes move, where they stand, to half
        as many slots while they fill at most half of them, down to slots.tail_min_slots, when the frames still to
        run would save more than a capture costs (a frame's saving taken as a quarter of its measured cost)."""
        least = self.cfg.slots.tail_min_slots
        if least == 0 or self.rollout.compiled or self.queue or self._may_propose():
            return
        busy = [s for s, r in enumerate(self.slots) if r is not None]
        size = len(self.slots)
        while size // 2 >= max(len(busy), least):
            size //= 2
        if not busy or size == len(self.slots):
            return
        t = self.rollout.t.cpu().numpy()  # the device is idle here: the last sync was just read
        left = max(len(self.slots[s].poses) - 1 - int(t[s]) for s in busy)
        frame_s = sum(self.rollout.part_s.values()) / max(1, self.rollout.advanced)
        if left * frame_s / 4 <= self.capture_s:
            return
        self._rebuild(self.rollout.frames, size, self.slots[busy[0]].slot_plan())
        self.shrinks += 1

    def _restart(self, overflow: dict[str, int]) -> None:
        """After a neighbour overflow: larger capacities, and the running episodes from their first frame."""
        self.restarts += 1
        self.rollout.grow_capacities(sorted(overflow))
        busy = [s for s, r in enumerate(self.slots) if r is not None]
        plans = [self.slots[s].slot_plan() for s in busy]
        with self.timer.phase("capture"):
            self._capture(plans[0])
            self.rollout.load(busy, plans)

    def _capture(self, park: SlotPlan) -> None:
        """The rollout's graphs captured on every slot parked on park's frame 0, and parked again afterwards (the
        capture's warm-up advanced them)."""
        every, parked = list(range(self.rollout.batch)), [SlotPlan(park.x0, park.poses[:1])] * self.rollout.batch
        self.rollout.load(every, parked)
        self.rollout.capture()
        self.rollout.load(every, parked)

    def _keep_busy(self) -> None:
        """File, propose and fill until a slot runs or nothing more can be proposed or planned; episodes still to be
        judged are judged here only when no slot runs (else after the next `advance`, beside the device)."""
        while True:
            self._file(judge=not any(r is not None for r in self.slots))
            self._propose()
            self._fill()
            if any(r is not None for r in self.slots) or not (self.queue or self._may_propose()):
                return

    @property
    def done(self) -> bool:
        """The target is reached: the episodes still in the slots are surplus."""
        return self.accepted >= self.wanted

    def run(self) -> None:
        """Until the target is reached, the attempts run out or the deadline passes; every write done."""
        try:
            self._keep_busy()
            while any(r is not None for r in self.slots) and not self.done:
                self.rollout.advance(self.cfg.slots.sync_every)
                self._file()  # host work while the device runs: the last read's verdicts, filing, proposals
                self._propose()
                with self.timer.phase("device_wait"):
                    t, first_frames, overflow = self.rollout.read_failures()
                if overflow:
                    self._restart(overflow)
                    continue
                self._retire(t, first_frames)
                self._keep_busy()
                self._shrink_tail()
            self._file()
        finally:
            with self.timer.phase("io_wait"):
                self.io.shutdown(wait=True)
            for w in self._writes:
                w.result()

    @property
    def attempts(self) -> int:
        return self.proposed

    @property
    def unused(self) -> int:
        """Proposed episodes neither counted nor written because the target was reached first (planned, rolled out
        in part or filed after it)."""
        return self.surplus + self.proposed - self.filed

    @property
    def counters(self) -> dict[str, dict[str, float]]:
        """The fixed projection's counters (one sync)."""
        return {"projection": self.rollout.fixed.read_stats()} if self.rollout is not None else {}

    @property
    def rollout_s(self) -> float:
        """Device time of the frames (the parts' sum)."""
        return sum(self.part_s.values())

    @property
    def part_s(self) -> dict[str, float]:
        """Device time per part of a frame, over every rollout of the run."""
        current = self.rollout.part_s if self.rollout is not None else {}
        return {k: v + current.get(k, 0.0) for k, v in self._retired_part_s.items()}

    def timing(self) -> dict[str, float]:
        """Seconds per host phase and per device part of a frame."""
        device = self.part_s if self.rollout is not None else {}  # no episode ran: no slots were made
        return {**{f"host_{k}_s": v for k, v in self.timer.seconds.items()},
                **{f"device_{k}_s": v for k, v in device.items()}}
