"""The finetune stage's work (`python -m stages.finetune`): one lerobot policy per LeRobot dataset of
`policy.datasets`, identical settings and seed (wc.policy.finetune) -> models/policy/<dataset>/ and the report, one
after another or side by side (`policy.side_by_side`: a process each); `stage_params` takes the `policy` section from
another file (`--policy FILE`).
"""

from __future__ import annotations

import os
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import torch

from wc.distributed.processes import pin_to_gpu, visible_gpus
from wc.config import ParamsError, load_section, params_hash, read_params
from wc.paths import FINETUNE
from wc.policy.comparison import FLAG, WARNING, expanded_equals_source
from wc.policy.finetune import dataset_metadata, finetune
from wc.policy.policy_config import PolicyConfig
from wc.reports import environment_info, write_json_atomic
from wc.smoke import smoke_label
from wc.worker_pool import cores_each, spawn_pool

SECTIONS = ["policy"]


def run(params: dict[str, Any], data_root: str | Path = FINETUNE["data_root"],
        out_root: str | Path = FINETUNE["out_root"], report: str | Path = FINETUNE["report"]) -> dict[str, Any]:
    """Train one policy per dataset in `policy.datasets`, write them under `out_root` and the report."""
    cfg = load_section(params, "policy", PolicyConfig)
    roots = {name: Path(data_root) / name for name in cfg.datasets}
    missing = [str(r) for r in roots.values() if not (r / "meta" / "info.json").is_file()]
    if missing:  # before any training: a missing second dataset should not cost the first one's run
        raise FileNotFoundError(f"finetune: no LeRobot dataset at {', '.join(missing)} (run the dataset stage first)")
    for root in roots.values():  # every dataset readable before any training
        dataset_metadata(root, cfg)
    start = time.perf_counter()
    digest = params_hash(params, SECTIONS)
    results = train_policies(roots, Path(out_root), cfg, {"params_hash": digest})
    equal = expanded_equals_source({name: r["episodes"] for name, r in results.items()})
    if equal:
        print(f"finetune: WARNING {WARNING}", flush=True)
    result = {
        FLAG: equal, "policy_type": cfg.type, "side_by_side": cfg.side_by_side, "steps": cfg.steps,
        "batch_size": cfg.batch_size, "seed": cfg.seed,
        "params_hash": digest, "wall_s": time.perf_counter() - start, "environment": environment_info(cfg.device),
        "datasets": {name: {k: r[k] for k in ("dataset", "episodes", "frames", "first_loss", "final_loss",
                                               "s_per_step_median", "train_s", "wall_s", "parameters", "pid")}
                     | {"gpu": r.get("gpu")}
                     | {"model": str(Path(out_root) / name)} for name, r in results.items()},
        **smoke_label(params, "finetune"),
    }
    write_json_atomic(report, result)
    return result


def train_policies(roots: dict[str, Path], out_root: Path, cfg: PolicyConfig,
                   meta: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """{dataset name: finetune's summary}, each policy trained on its dataset with `cfg`; with `cfg.side_by_side`
    all at once, each in a spawned process that ends with this one (the same seed and settings: the same policies),
    on a GPU of its own where `policy.device` is cuda and the host has several (`arm_gpus`)."""
    if not cfg.side_by_side or len(roots) < 2:
        return {name: _finetune_here(root, out_root / name, cfg, meta) for name, root in roots.items()}
    gpus = arm_gpus(len(roots), cfg.device, visible_gpus() if cfg.device == "cuda" else [])
    with ExitStack() as stack:
        pools = [stack.enter_context(spawn_pool(1, _start_arm, (gpu, cores_each(len(roots))))) for gpu in gpus]
        futures = {name: (pool.submit(_finetune_here, root, out_root / name, cfg, meta), gpu)
                   for pool, gpu, (name, root) in zip(pools, gpus, roots.items())}
        return {name: future.result() | {"gpu": gpu} for name, (future, gpu) in futures.items()}


def arm_gpus(arms: int, device: str, gpus: list[str]) -> list[str | None]:
    """The GPU each side-by-side policy trains on: round robin over `gpus` where `device` is cuda and there are
    several; None (the device as configured, shared) otherwise."""
    if device != "cuda" or len(gpus) < 2:
        return [None] * arms
    return [gpus[i % len(gpus)] for i in range(arms)]


def _start_arm(gpu: str | None, threads: int) -> None:
    """A side-by-side process's start-up: its GPU (if any) and its share of the cores."""
    pin_to_gpu(gpu)
    torch.set_num_threads(threads)


def _finetune_here(root: Path, out: Path, cfg: PolicyConfig, meta: dict[str, Any]) -> dict[str, Any]:
    """finetune's summary and the id of the process that trained the policy."""
    return finetune(root, out, cfg, meta=meta) | {"pid": os.getpid()}


def stage_params(path: str | Path, overrides: list[str], policy_file: str | Path | None = None) -> dict[str, Any]:
    """Params from `path`, with the `policy` section taken from `policy_file` when given."""
    if policy_file is None:
        return read_params(path, overrides)
    own = [o for o in overrides if o.startswith("policy.")]
    params = read_params(path, [o for o in overrides if o not in own])
    fragment = read_params(policy_file, own)
    if "policy" not in fragment:
        raise ParamsError(f"{policy_file}: missing section 'policy'")
    params["policy"] = fragment["policy"]
    return params


def finetune_summary(r: dict[str, Any]) -> str:
    """The line `python -m stages.finetune` prints."""
    per = "; ".join(f"{n}: loss {d['first_loss']:.4g} -> {d['final_loss']:.4g}, {d['s_per_step_median']:.3f} s/step"
                    for n, d in r["datasets"].items())
    return (f"finetune: {r['policy_type']} {r['steps']} steps x {len(r['datasets'])} datasets ({per}); "
            f"{r['wall_s']:.0f} s")
