"""Where a slot-engine frame's device time goes, piece by piece (each timed alone, synchronised), at a few slot counts:
the network, the joint projection's edge passes, push out and self-contact pairs and passes, the bounded step's pair
queries and passes, the rollback's crossing tests. The pair counts the projection met come with it, to size the
static capacities (`expand.slots.*_capacity`).

    python -m benchmarks.slot_frame_profile [--params params.yaml] [--set key=value ...] [--device cuda]
        [--slots 64,256] [--frames 12] --out FILE.json
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import torch

from benchmarks.expand_smoke import slot_models
from wc.config import add_params_arguments, read_params
from wc.expand.body_contacts import push_out
from wc.expand.constraints import edge_pass
from wc.expand.slot_stage import SlotModel
from wc.reports import environment_info, write_json_atomic


def timed(fn: Any, repeats: int = 3) -> float:
    """Median seconds of fn() on the device."""
    times = []
    for _ in range(repeats):
        torch.cuda.synchronize() if torch.cuda.is_available() else None
        started = time.perf_counter()
        fn()
        torch.cuda.synchronize() if torch.cuda.is_available() else None
        times.append(time.perf_counter() - started)
    return sorted(times)[len(times) // 2]


@torch.no_grad()
def profile(model: SlotModel, plan: Any, frames: int) -> dict[str, Any]:
    rollout = model.rollout(frames + 2)
    slots = list(range(rollout.batch))
    rollout.load(slots, [plan] * rollout.batch)
    rollout.advance(frames)  # eager: a state some frames into the plan
    fixed, dt = model.fixed, model.dt
    x_prev = rollout.x.clone()
    rollout._network()
    x, v = rollout._x.clone(), rollout._v.clone()
    link = rollout._next[:, rollout.link_columns]
    bodies = fixed.bodies.pose(link, x)
    inv = torch.ones(x.shape[:2], device=x.device)
    fixed.reset_stats()
    out = {"network_s": timed(rollout._network)}
    out["edge_pass_s"] = timed(lambda: edge_pass(x.clone(), inv, fixed.colours, fixed.lo, fixed.hi, torch.zeros_like(x)))
    out["push_out_s"] = timed(lambda: push_out(x[:, fixed.bodies.cloth], bodies))
    out["self_contact_pairs_s"] = timed(lambda: fixed._self_contact_pairs(x))
    out["joint_s"] = timed(lambda: fixed.joint(x_prev, x, v, link, dt))
    jx, jv = fixed.joint(x_prev, x, v, link, dt)
    if fixed.bounded is not None:
        dropped = torch.zeros(x.shape[0], dtype=torch.int32, device=x.device)
        step = (jx - x_prev).contiguous()
        out["bounded_pairs_s"] = timed(lambda: fixed.bounded.pairs(fixed.bvh, x_prev, step, dropped))
        e, i, j, bound, valid = fixed.bounded.pairs(fixed.bvh, x_prev, step, dropped)
        out["bounded_pairs"] = int(valid.sum())
        out["bounded_pair_slots"] = int(valid.numel())
        out["bounded_passes_s"] = timed(lambda: fixed.bounded._project(step.clone(), e, i, j, bound, valid))
        out["bounded_s"] = timed(lambda: fixed.bounded.apply(fixed.bvh, x_prev, jx, jv, dt, fixed.stats))
    out["crossing_test_s"] = timed(lambda: fixed.rollback.crossings(fixed.bvh, jx))
    out["rollback_s"] = timed(lambda: fixed.rollback.apply(fixed.bvh, x_prev, jx, jv, fixed.stats))
    out["checks_s"] = timed(rollout._checks)
    out["stats"] = fixed.read_stats()
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--model", default="models/pretrained/worldcontact-lift-handle")
    parser.add_argument("--slots", default="64,256")
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--out", default="reports/slot_frame_profile.json")
    args = parser.parse_args(argv)
    params = read_params(args.params, [*args.overrides, f"expand.device={args.device}"])
    rows = []
    with slot_models(params, args.model, args.frames + 2) as (plan, make):
        for slots in (int(s) for s in args.slots.split(",")):
            row = {"slots": slots, **profile(make(slots), plan, args.frames)}
            rows.append(row)
            print(row, flush=True)
            write_json_atomic(args.out, {"benchmark": "slot_frame_profile", "environment": environment_info(args.device),
                                         "rows": rows})


if __name__ == "__main__":
    main()
