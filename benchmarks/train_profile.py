"""Where the static-shape training step spends GPU time: the torch profiler over a few eager static steps.

    python -m benchmarks.train_profile --store data/source/trajectories.zarr [--batch 8] [--steps 3] [--compile]
Prints the top CUDA kernels by total time and the kernel count per step.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import torch
from torch.profiler import ProfilerActivity, profile

from benchmarks.train_speed import Setting
from wc.config import read_params
from wc.train.capacity import data_capacities
from wc.train.loop import SegmentRollout
from wc.train.static_step import LayoutStep, StepSettings, make_optimizer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--store", default="data/source/trajectories.zarr")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--compile", action="store_true")
    args = parser.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    s = Setting(args.store, read_params(args.params), args.batch, args.steps, device)
    model = s.model()
    cfg = replace(s.cfg, static=True, compile=args.compile, cuda_graph=False, autocast_bf16=True)
    capacities, _ = data_capacities(s.store, s.phases, s.model_cfg, s.layout_for, cfg.neighbor_headroom, device)
    step = LayoutStep(model, SegmentRollout(model), make_optimizer(model, cfg, device), s.layout,
                      s.resident.layouts[0], model.fixed_neighbors(s.layout, capacities), None,
                      StepSettings.of(cfg, s.store.dt))
    starts = [s.resident.batch_location(b)[1] for b in s.batches]
    for k in range(2):
        step.forward_backward(starts[k]); step.update()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for k in range(args.steps):
            step.forward_backward(starts[k]); step.update()
        torch.cuda.synchronize()
    kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    total = sum(e.device_time for e in kernels)
    print(f"kernels per step {len(kernels) / args.steps:.0f}, GPU time per step {total / args.steps / 1e3:.1f} ms")
    print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=25, max_name_column_width=70))


if __name__ == "__main__":
    main()
