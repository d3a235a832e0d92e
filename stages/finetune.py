"""Stage `finetune`: one lerobot policy per LeRobot dataset (data/lerobot/{source,expanded}), identical
settings and seed -> models/policy/{source,expanded}/ and reports/finetune.json.

    python -m stages.finetune [--params params.yaml] [--set policy.steps=50 ...]
    python -m stages.finetune --params params/gpu.yaml --policy params/policy_pi05.yaml   # pi0.5 recipe
    python -m stages.finetune --params params/gpu.yaml --policy params/policy_act_gpu.yaml   # ACT, one GPU

`--policy FILE` takes the `policy` section from FILE instead (`--set policy.*` then applies to it).

The work is `wc.policy.finetune.finetune` (importable, used by the tests), which trains with lerobot's own
`lerobot-train` code in this process (one GPU or the CPU; for several GPUs run `lerobot-train` under
`accelerate launch` per dataset); params `policy` (wc.policy.policy_config) say which policy, which datasets
and the recipe.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from wc.cli import run_cli
from wc.config import ParamsError, add_params_arguments, load_section, params_hash, read_params
from wc.policy.comparison import FLAG, WARNING, expanded_equals_source
from wc.policy.finetune import finetune
from wc.policy.policy_config import PolicyConfig
from wc.reports import environment_info, write_json_atomic

SECTIONS = ["policy"]


def run(params: dict[str, Any], data_root: str | Path = "data/lerobot", out_root: str | Path = "models/policy",
        report: str | Path = "reports/finetune.json") -> dict[str, Any]:
    """Train one policy per dataset in `policy.datasets`, write them under `out_root` and the report."""
    cfg = load_section(params, "policy", PolicyConfig)
    roots = {name: Path(data_root) / name for name in cfg.datasets}
    missing = [str(r) for r in roots.values() if not (r / "meta" / "info.json").is_file()]
    if missing:  # before any training: a missing second dataset should not cost the first one's run
        raise FileNotFoundError(f"finetune: no LeRobot dataset at {', '.join(missing)} (run the dataset stage first)")
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--policy", default=None, metavar="FILE", help="take the policy section from FILE")
    parser.add_argument("--data-root", default="data/lerobot")
    parser.add_argument("--out-root", default="models/policy")
    parser.add_argument("--report", default="reports/finetune.json")
    args = parser.parse_args(argv)
    r = run(stage_params(args.params, args.overrides, args.policy), args.data_root, args.out_root, args.report)
    per = "; ".join(f"{n}: loss {d['first_loss']:.4g} -> {d['final_loss']:.4g}, {d['s_per_step_median']:.3f} s/step"
                    for n, d in r["datasets"].items())
    print(f"finetune: {r['policy_type']} {r['steps']} steps x {len(r['datasets'])} datasets ({per}); {r['wall_s']:.0f} s")


if __name__ == "__main__":
    run_cli(main, "finetune")
