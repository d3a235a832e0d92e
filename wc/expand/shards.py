"""`expand.shards`: the expansion split into independent shards, run on the devices of this host, concatenated.

With S shards the wanted generated episodes and the attempts are split into S fixed shares (`share`); shard i is a
complete expansion of its share (wc.expand.stage.expand_share, either engine) with its own plan seeds
(wc.expand.plan.plan_seed: from expand.seed and i), writing temporary stores. The shards are the units of the
`processes` executor (section `processes`: one process per GPU, a shard at a time each), and their stores are
concatenated in shard order into the outputs, each written atomically: the outputs depend on expand.shards, not on
how many devices ran them.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from wc.atomic import temporary_sibling
from wc.config import load_section
from wc.data.store import concatenate_stores
from wc.distributed import Unit, WorkerSpec, drive, open_executor
from wc.expand.config import ExpandConfig

SUMMED = ("attempts", "infeasible_plans", "generated", "accepted", "rejected", "frames_generated", "rollout_s",
          "slot_loads", "restarts", "tail_shrinks", "unused_proposals")  # report counts that add up over the shards
LISTED = ("rejected_episodes", "infeasible")  # report lists concatenated in shard order


def share(total: int, shards: int, shard: int) -> int:
    """Shard `shard`'s fixed share of `total` (episodes or attempts): the first total % shards shards take one more."""
    return total // shards + (shard < total % shards)


def shard_outputs(folder: Path, shard: int, keep_rejected: bool) -> tuple[Path, Path, Path | None]:
    """Shard `shard`'s temporary accepted store, report and rejected store (None: not kept) in `folder`."""
    return (folder / f"shard_{shard}.zarr", folder / f"shard_{shard}.json",
            folder / f"shard_{shard}_rejected.zarr" if keep_rejected else None)


def shard_worker(expand_share: Callable[..., dict[str, Any]], params: dict[str, Any], model_dir: str, store: str,
                 folder: str, keep_rejected: bool) -> Callable[[int], dict[str, Any]]:
    """The worker of the shard units: shard i's expansion into `folder`; its report and the GPU it ran on."""

    def run(shard: int) -> dict[str, Any]:
        out, report, rejected = shard_outputs(Path(folder), shard, keep_rejected)
        result = expand_share(params, model_dir, Path(store), out, report, rejected, shard)
        return {"report": result, "gpu": os.environ.get("CUDA_VISIBLE_DEVICES"), "pid": os.getpid()}

    return run


class ShardRuns:
    """The shards as one stream of units (wc.distributed.streams), all proposed at once, filed in shard order."""

    def __init__(self, worker: WorkerSpec, shards: int) -> None:
        self.worker, self.shards = worker, shards
        self.proposed = 0
        self.results: list[dict[str, Any]] = []

    def next_unit(self) -> Unit | None:
        if self.proposed == self.shards:
            return None
        self.proposed += 1
        return Unit(self.worker, self.proposed - 1, f"expand shard {self.proposed - 1}")

    def file(self, result: dict[str, Any]) -> None:
        self.results.append(result)


def merged(a: Any, b: Any) -> Any:
    """Two shards' projection counters together: maxima (keys max_*) the larger, other numbers summed, dicts per key."""
    if a is None or b is None:
        return b if a is None else a
    return {k: (max(a[k], v) if k.startswith("max_") else merged(a[k], v) if isinstance(v, dict) else a[k] + v)
            if k in a else v for k, v in b.items()}


def combined_report(reports: list[dict[str, Any]], placed: list[dict[str, Any]], wall_s: float) -> dict[str, Any]:
    """The stage's report from the shards' (in shard order): counts summed, lists concatenated, rates over the whole
    wall time, and a `shards` entry per shard with where it ran and its timing."""
    first = reports[0]
    out = {**first, **{k: sum(r[k] for r in reports) for k in SUMMED if k in first},
           **{k: [e for r in reports for e in r[k]] for k in LISTED}}
    out["rejections"] = {k: sum(r["rejections"].get(k, 0) for r in reports) for k in first["rejections"]}
    for key in ("projection_stats", "untangle_stats"):
        total = None
        for r in reports:
            total = merged(total, r[key])
        out[key] = total
    accepted, generated = out["accepted"], out["generated"]
    out.update(wanted_generated=sum(r["wanted_generated"] for r in reports),
               acceptance_rate=accepted / generated if generated else None,
               expanded_total=first["source_episodes"] + accepted,
               target_reached=first["source_episodes"] + accepted >= first["target_trajectories"],
               stopped_early=any(r["stopped_early"] for r in reports),
               model_frames_per_s=out["frames_generated"] / out["rollout_s"] if out["rollout_s"] else None,
               wall_s=wall_s, trajectories_per_min=60.0 * generated / wall_s, accepted_per_min=60.0 * accepted / wall_s)
    out.pop("timing", None)
    out["shards"] = [{"shard": i, "gpu": p["gpu"], "process": p["pid"], "device": r["device"], "wall_s": r["wall_s"],
                      **{k: r[k] for k in ("wanted_generated", "attempts", "generated", "accepted")},
                      **({"timing": r["timing"]} if "timing" in r else {})}
                     for i, (r, p) in enumerate(zip(reports, placed))]
    return out


def expand_in_shards(params: dict[str, Any], expand_share: Callable[..., dict[str, Any]], model_dir: Path,
                     store: Path, out: Path, rejected_out: Path | None, params_hash: str,
                     model: dict[str, Any]) -> dict[str, Any]:
    """Run expand.shards shards of `expand_share` (module docstring) and write `out` (and `rejected_out`, None: not
    kept); returns the stage's report (its params hash and model record the caller's)."""
    shards = load_section(params, "expand", ExpandConfig).shards
    started = time.perf_counter()
    folder = temporary_sibling(out)
    folder.mkdir(parents=True)
    try:
        worker = WorkerSpec(f"expand-shards:{folder.name}", shard_worker,
                            (expand_share, params, str(model_dir), str(store), str(folder), rejected_out is not None))
        runs = ShardRuns(worker, shards)
        with open_executor("processes", params, gpu=True) as executor:
            for _ in drive(executor, [runs], shards):
                pass
        for target, index in ((out, 0), (rejected_out, 2)):
            if target is not None:
                concatenate_stores([shard_outputs(folder, i, True)[index] for i in range(shards)], target)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    result = combined_report([r["report"] for r in runs.results], runs.results, time.perf_counter() - started)
    result.update(executor=executor.report(), out=str(out), params_hash=params_hash, model=model,
                  rejected_out=str(rejected_out) if rejected_out is not None else None)
    return result
