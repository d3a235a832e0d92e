"""The finetune stage's work (`python -m stages.finetune`): one lerobot policy per LeRobot dataset of
`policy.datasets`, identical settings and seed (wc.policy.finetune) -> models/policy/<dataset>/ and the report;
`stage_params` takes the `policy` section from another file (`--policy FILE`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from wc.config import ParamsError, load_section, params_hash, read_params
from wc.paths import FINETUNE
from wc.policy.comparison import FLAG, WARNING, expanded_equals_source
from wc.policy.finetune import dataset_metadata, finetune
from wc.policy.policy_config import PolicyConfig
from wc.reports import environment_info, write_json_atomic
from wc.smoke import smoke_label

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
    results = {name: finetune(root, Path(out_root) / name, cfg, meta={"params_hash": digest})
               for name, root in roots.items()}
    equal = expanded_equals_source({name: r["episodes"] for name, r in results.items()})
    if equal:
        print(f"finetune: WARNING {WARNING}", flush=True)
    result = {
        FLAG: equal, "policy_type": cfg.type, "steps": cfg.steps, "batch_size": cfg.batch_size, "seed": cfg.seed,
        "params_hash": digest, "wall_s": time.perf_counter() - start, "environment": environment_info(cfg.device),
        "datasets": {name: {k: r[k] for k in ("dataset", "episodes", "frames", "first_loss", "final_loss",
                                               "s_per_step_median", "train_s", "wall_s", "parameters")}
                     | {"model": str(Path(out_root) / name)} for name, r in results.items()},
        **smoke_label(params, "finetune"),
    }
    write_json_atomic(report, result)
    return result


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
