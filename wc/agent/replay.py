"""Plans (frame-0 state + actions) replayed in Newton, and Newton's agreement with itself on them.

A plan's outcome is only as reproducible as the solver: VBD with few iterations per substep does not converge, so the
other worlds of a batch (their colour order spans the worlds) and float-rounding differences move a plan's rollout,
and the task's verdict (did the strap stay in the pads) can flip. `self_agreement` replays the plans again per noise
scale, in another batch order and from frame-0 positions + N(0, scale^2), and says how often Newton's verdict stays
the same: the ceiling of any check that scores a model against one Newton replay (the teacher check), and the measure
`benchmarks.newton_convergence` charts against the solver's cost.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from tqdm import tqdm

from wc.agent.runner import TaskWorld, execute, judge, reset_batch
from wc.dynamics import ObjectState
from wc.tasks.base import EpisodeSpec
from wc.validate.config import ValidateConfig
from wc.validate.failure_detail import failure_detail
from wc.validate.predicates import Episode


@dataclass
class Plan:
    """What Newton needs to replay an episode: its spec (for the task's verdict), frame-0 state and actions."""

    spec: EpisodeSpec
    x0: np.ndarray  # (V, 3) [m]
    v0: np.ndarray  # (V, 3) [m/s]
    action: np.ndarray  # (T, 14)
    # (T, V, 3) [m]: a trajectory to measure the replay against, or a function that reads it (called when the plan's
    # batch is judged, so that a long list of plans does not hold every reference at once)
    reference_x: np.ndarray | Callable[[], np.ndarray] | None = None

    def reference(self) -> np.ndarray | None:
        return self.reference_x() if callable(self.reference_x) else self.reference_x


def plan_specs(world: TaskWorld, specs: list[EpisodeSpec], worlds: int) -> list[Plan]:
    """The specs reset, settled and planned as the agent does, `worlds` at a time; the unplannable ones are left out."""
    plans = []
    for first in range(0, len(specs), worlds):
        runnable, _ = reset_batch(world, specs[first:first + worlds])
        plans += [Plan(spec, state.x, state.v, actions) for spec, state, actions in runnable]
    return plans


@dataclass
class Replay:
    """Newton's rollout of one plan and the verdict of the source data's checks on it (its own frames only)."""

    verdict: str  # "accepted" or the first failing check
    failure_frame: int | None
    x: np.ndarray | None  # (T, V, 3) [m]; None unless kept
    rms_error_m: np.ndarray | None  # (T,) RMS vertex distance to the plan's reference_x [m]; None without one
    detail: dict[str, object]  # a blow_up's criterion or a penetration's body (wc.validate.failure_detail); {} else


def replay(world: TaskWorld, plans: list[Plan], validate_cfg: ValidateConfig, frame_dt_s: float,
           perturb_m: float = 0.0, seed: int = 0, keep_x: bool = True, desc: str = "newton replay") -> list[Replay]:
    """Roll the plans out in Newton, `sim.worlds` at a time (a batch runs to its longest plan; each plan is judged on
    its own frames), from frame-0 positions with N(0, perturb_m^2) noise (seeded) added to every coordinate. Newton's
    positions are kept only if `keep_x` (64 plans at paper scale hold ~2 GB)."""
    if not perturb_m >= 0:
        raise ValueError(f"newton replay: perturb_m must be >= 0 m, got {perturb_m}")
    rng, out = np.random.default_rng(seed), []
    for first in tqdm(range(0, len(plans), world.sim.worlds), desc=desc, unit="batch"):
        batch = plans[first:first + world.sim.worlds]
        starts = [ObjectState((p.x0 + rng.normal(0.0, perturb_m, p.x0.shape)).astype(np.float32)
                              if perturb_m > 0 else p.x0, p.v0) for p in batch]
        rollouts = execute(world, starts, [p.action for p in batch], None)[0]
        for plan, (x, v) in zip(batch, rollouts):
            frames = len(plan.action)
            x, v = x[:frames], v[:frames]
            poses = world.scene.link_poses(plan.action)
            failure = judge(world, plan.spec, x, v, plan.action, poses, validate_cfg, frame_dt_s)
            reference = plan.reference()
            rms = None if reference is None else np.sqrt(np.square(x - reference[:frames]).sum(-1).mean(-1))
            detail = {} if failure is None else failure_detail(
                world.scene, Episode(x, v, plan.action, poses, frame_dt_s), validate_cfg, *failure)
            out.append(Replay("accepted" if failure is None else failure[0],
                              None if failure is None else int(failure[1]), x if keep_x else None, rms, detail))
    return out


def same_verdict(a: str, b: str) -> bool:
    """Two verdicts agree: both accept, or both reject (for whatever reason)."""
    return a == b or "accepted" not in (a, b)


def share(hits: list[bool]) -> float | None:
    return sum(hits) / len(hits) if hits else None


def self_agreement(world: TaskWorld, plans: list[Plan], first: list[Replay], validate_cfg: ValidateConfig,
                   frame_dt_s: float, scales_m: list[float], seed: int
                   ) -> tuple[list[dict[str, object]], list[list[dict[str, object]]]]:
    """Newton's verdicts again, once per scale: another batch order (seeded) and frame-0 positions + N(0, scale^2).
    `first` must hold Newton's positions (`replay(..., keep_x=True)`). Returns, per scale, the share of plans whose
    verdict stayed that of `first`, the flips and the mean RMS distance to `first`; and per plan its repeats (scale,
    verdict, distance), in `plans` order."""
    if any(not s >= 0 for s in scales_m):
        raise ValueError(f"newton self-agreement: scales must be >= 0 m, got {scales_m}")
    summary, repeats = [], [[] for _ in plans]
    for k, scale in enumerate(scales_m):
        order = np.random.default_rng([seed, k]).permutation(len(plans))
        against_first = [replace(plans[i], reference_x=first[i].x) for i in order]
        again = replay(world, against_first, validate_cfg, frame_dt_s, scale, seed + 1 + k, keep_x=False,
                       desc=f"newton again ({scale:g} m)")
        same, drift = [], []
        for i, repeat in zip(order, again):
            drift.append(float(repeat.rms_error_m.mean()))
            repeats[i].append({"perturb_m": scale, "newton": repeat.verdict, "mean_rms_to_first_m": drift[-1]})
            same.append(same_verdict(first[i].verdict, repeat.verdict))
        flipped = Counter(f"{first[i].verdict} -> {r.verdict}" for i, r, ok in zip(order, again, same) if not ok)
        summary.append({"perturb_m": scale, "plans": len(same), "agreement": share(same),
                        "flips": len(same) - sum(same), "flipped": dict(flipped),
                        "mean_rms_to_first_m": float(np.mean(drift))})
    return summary, repeats
