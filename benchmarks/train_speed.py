"""Training speed: the reference path against the static-shape path, in one process, on the same batches.

    python -m benchmarks.train_speed --params params.yaml --store data/source/trajectories.zarr --tag h100
        [--settings default:8,default:32,paper:1] [--paper-params params/gpu.yaml] [--steps 30]
        [--variants static_eager,static_compiled,static_graphed,static_graphed_bf16] [--rollout-frames 25]
        [--budget-s 540] [--out-dir reports/gpu]
    -> <out-dir>/train_speed_<tag>.json (rewritten after every row) + .md

Per setting (scene:batch; `default` is the --store's data, `paper` a synthetic episode of the --paper-params scene,
the 20k-vertex bag; windows of W = train.window frames of the store's largest layout):
1. the first batch's loss and gradients through both paths from the same weights (fp32, no update): their
   relative difference;
2. `--steps` optimisation steps of the reference path (windows read from the store, pair-list neighbours, eager,
   bf16 autocast on CUDA as params/gpu.yaml trains) and of each static variant, on the same pre-drawn batches, after
   warm-up steps (compilation and graph capture are timed separately): steps/s, peak memory;
3. single rollouts (B = 1, no gradients) of `--rollout-frames` frames: the reference rollout (Verlet-skin neighbour
   reuse, bf16 on CUDA) against `StaticRollout` (CUDA-graphed, bf16): ms per step.
`new_steps_per_s` is the fastest static variant, `speedup` = new / old. Every row catches errors (e.g. out of
memory) and records them; rows that would start after --budget-s are skipped.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import tempfile
import time
import traceback
from contextlib import nullcontext
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from wc.config import add_params_arguments, load_section, read_params
from wc.data.store import TrajectoryStore
from wc.model.config import ModelConfig
from wc.model.rollout import rollout
from wc.model.static_rollout import StaticRollout
from wc.model.worldcontact import WorldContact
from wc.reports import environment_info, write_report_atomic
from wc.train.capacity import data_capacities
from wc.train.config import TrainConfig
from wc.train.data import LayoutBatchSampler, data_scales, phases_of, read_phase_window, windows_of
from wc.train.evaluation import segment_loss
from wc.train.loop import SegmentRollout, _layouts, optimisation_step
from wc.train.resident import ResidentWindows
from wc.train.static_step import LayoutStep, StepSettings, make_optimizer, set_learning_rate

VARIANTS = {  # name -> (compile, cuda_graph, bf16, dynamic shapes in the compiled graph)
    "static_eager": (False, False, False, True),
    "static_compiled": (True, False, True, False),
    "static_graphed": (False, True, True, True),
    "static_graphed_fp32": (True, True, False, False),
    "static_graphed_bf16": (True, True, True, False),
    "static_graphed_bf16_dynamic": (True, True, True, True),
}
TARGETS = {"default_batch8_speedup": 10.0, "default_batch8_steps_per_s": 27.0, "paper_batch1_speedup": 2.0,
           "paper_batch1_s_per_step": 0.25}


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def peak_gib(device: torch.device) -> float:
    return torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else float("nan")


def reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


class Setting:
    """One (store, batch size): the windows of its largest layout, batches drawn once, model factory."""

    def __init__(self, store_path: Path, params: dict[str, Any], batch: int, steps: int, device: torch.device) -> None:
        self.store = TrajectoryStore(store_path)
        self.model_cfg = load_section(params, "model", ModelConfig)
        self.cfg = replace(load_section(params, "train", TrainConfig), batch_size=batch, device=str(device))
        self.device = device
        phases = phases_of(self.store, "train") or phases_of(self.store, "val")
        windows = windows_of(phases, self.cfg.window)
        largest = max({w.phase.layout for w in windows}, key=lambda k: sum(w.phase.layout == k for w in windows))
        self.windows = [w for w in windows if w.phase.layout == largest]
        self.phases = [p for p in phases if p.layout == largest]
        self.scales = data_scales(self.store, self.phases, self.cfg.stats_episodes)
        self.layout_for = _layouts(self.store, self.model_cfg, device)
        self.layout = self.layout_for(largest)
        sampler = iter(LayoutBatchSampler(self.windows, batch, seed=0))
        self.batches = [next(sampler) for _ in range(steps + 3)]  # 3 warm-up batches first
        self.resident = ResidentWindows(self.store, self.windows, self.cfg.window, device)

    def model(self) -> WorldContact:
        torch.manual_seed(0)
        return WorldContact(self.model_cfg, **asdict(self.scales)).to(self.device).train()

    def host_batch(self, indices: list[int]) -> tuple[torch.Tensor, ...]:
        """The reference path's batch: windows read from the store, stacked, copied to the device."""
        arrays = [read_phase_window(self.store, self.windows[i].phase, self.windows[i].start, self.cfg.window)
                  for i in indices]
        return tuple(torch.from_numpy(np.stack([a[k] for a in arrays])).to(self.device) for k in ("x", "v", "poses"))


def time_reference(s: Setting, bf16: bool) -> dict[str, Any]:
    model = s.model()
    cfg = replace(s.cfg, autocast_bf16=bf16)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-5, betas=cfg.betas, weight_decay=cfg.weight_decay)
    runner = SegmentRollout(model)
    reset_peak(s.device)
    walls, losses = [], []
    for k, indices in enumerate(s.batches):
        sync(s.device)
        t = time.perf_counter()
        x, v, poses = s.host_batch(indices)
        losses.append(optimisation_step(runner, optimizer, s.layout, x, v, poses, s.store.dt, None, cfg))
        if k >= 3:
            walls.append(time.perf_counter() - t)
    step_s = statistics.median(walls)
    return {"steps_per_s": 1.0 / step_s, "s_per_step": step_s, "peak_memory_gib": peak_gib(s.device),
            "bf16": bf16 and s.device.type == "cuda", "finite": bool(np.isfinite(losses).all())}


def time_static(s: Setting, variant: str) -> dict[str, Any]:
    compile_, graph, bf16, dynamic = VARIANTS[variant]
    model = s.model()
    cfg = replace(s.cfg, static=True, compile=compile_, cuda_graph=graph, autocast_bf16=bf16, compile_dynamic=dynamic)
    optimizer = make_optimizer(model, cfg, s.device)
    set_learning_rate(optimizer, 1e-5)
    capacities, measured = data_capacities(s.store, s.phases, s.model_cfg, s.layout_for, cfg.neighbor_headroom, s.device)
    step = LayoutStep(model, SegmentRollout(model), optimizer, s.layout, s.resident.layouts[0],
                      model.fixed_neighbors(s.layout, capacities), None, StepSettings.of(cfg, s.store.dt))
    reset_peak(s.device)
    walls, losses, warmup = [], [], 0.0
    for k, indices in enumerate(s.batches):
        li, starts = s.resident.batch_location(indices)
        sync(s.device)
        t = time.perf_counter()
        loss, overflow = step.forward_backward(starts).tolist()  # the static trainer's one sync
        if overflow:
            raise RuntimeError(f"neighbour overflow at step {k} with capacities {capacities}")
        step.update()
        losses.append(loss)
        sync(s.device)
        if k >= 3:
            walls.append(time.perf_counter() - t)
        else:
            warmup += time.perf_counter() - t
    step_s = statistics.median(walls)
    return {"steps_per_s": 1.0 / step_s, "s_per_step": step_s, "peak_memory_gib": peak_gib(s.device),
            "warmup_s": warmup, "compile": compile_, "compile_dynamic": compile_ and dynamic,
            "cuda_graph": graph and s.device.type == "cuda",
            "bf16": bf16 and s.device.type == "cuda", "finite": bool(np.isfinite(losses).all()),
            "capacities": {k: [c.max_neighbors, c.cell_capacity] for k, c in capacities.items()},
            "measured_neighbors": measured}


def first_batch_agreement(s: Setting) -> dict[str, float]:
    """Loss and gradients of the first batch through both paths from the same weights, fp32, no update."""
    model = s.model()
    capacities, _ = data_capacities(s.store, s.phases, s.model_cfg, s.layout_for, s.cfg.neighbor_headroom, s.device)
    x, v, poses = s.host_batch(s.batches[0])
    grads = []
    for neighbors in (None, model.fixed_neighbors(s.layout, capacities)):
        model.zero_grad(set_to_none=True)
        torch.manual_seed(1)
        xp, vp = SegmentRollout(model)(s.layout, x[:, 0], v[:, 0], poses, s.store.dt, None, neighbors)
        loss = segment_loss(xp, vp, x[:, 1:], v[:, 1:], s.cfg.lambda_x, s.cfg.lambda_v)
        loss.backward()
        grads.append((float(loss.detach()), torch.cat([p.grad.flatten() for p in model.parameters()
                                                       if p.grad is not None])))
    (loss_ref, g_ref), (loss_new, g_new) = grads
    return {"loss_relative_difference": abs(loss_new - loss_ref) / abs(loss_ref),
            "gradient_relative_difference": float((g_new - g_ref).norm() / g_ref.norm())}


@torch.no_grad()
def time_rollouts(s: Setting, frames: int, repeats: int = 5) -> dict[str, Any]:
    """ms per step of one scene's rollout: reference (Verlet reuse, bf16 on CUDA) and StaticRollout (graphed)."""
    model = s.model().eval()
    phase = max(s.phases, key=lambda p: p.stop - p.start)
    frames = min(frames, phase.stop - phase.start - 1)
    a = {k: torch.from_numpy(np.ascontiguousarray(v))[None].to(s.device)
         for k, v in read_phase_window(s.store, phase, phase.start, frames + 1).items()}
    bf16 = torch.autocast("cuda", dtype=torch.bfloat16) if s.device.type == "cuda" else nullcontext()
    capacities, _ = data_capacities(s.store, s.phases, s.model_cfg, s.layout_for, s.cfg.neighbor_headroom, s.device)
    static = StaticRollout(model, capacities, s.store.dt, compile=True, cuda_graph=True, autocast_bf16=True)

    def reference() -> torch.Tensor:
        with bf16:
            return rollout(model, s.layout, a["x"][:, 0], a["v"][:, 0], a["poses"], s.store.dt)[0]

    def fast() -> torch.Tensor:
        return static.rollout(s.layout, a["x"][:, 0], a["v"][:, 0], a["poses"])[0]

    out: dict[str, Any] = {"frames": frames}
    results = {}
    for name, fn in (("reference", reference), ("static", fast)):
        fn()  # warm-up: compilation, capture
        walls = []
        for _ in range(repeats):
            sync(s.device)
            t = time.perf_counter()
            results[name] = fn()
            sync(s.device)
            walls.append(time.perf_counter() - t)
        out[f"{name}_ms_per_step"] = 1e3 * statistics.median(walls) / frames
    ref, new = results["reference"].float(), results["static"].float()
    out["speedup"] = out["reference_ms_per_step"] / out["static_ms_per_step"]
    out["position_rms_difference_m"] = float((ref - new).square().mean().sqrt())
    out["capacity_growths"] = static.growths
    return out


def markdown(report: dict[str, Any]) -> str:
    env = report["environment"]
    lines = [f"# Training speed: reference vs static-shape path ({report['tag']})", "",
             f"Device {env.get('device_name', env.get('device'))}, torch {env.get('torch')}, warp {env.get('warp')}; "
             f"W = {report['window']}, {report['steps']} timed steps after 3 warm-up steps, same batches.", "",
             "| setting | vertices | batch | old steps/s | new steps/s | speedup | new s/step | old / new peak GiB | "
             "first-batch loss / grad rel. diff |", "|---|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        if "error" in r or "skipped" in r:
            lines.append(f"| {r['setting']} | | {r.get('batch', '')} | {r.get('error', r.get('skipped'))[:80]} |"
                         " | | | | |")
            continue
        agree = r.get("agreement", {})
        lines.append(
            f"| {r['setting']} | {r['vertices']} | {r['batch']} | {r['old_steps_per_s']:.2f} | {r['new_steps_per_s']:.2f} "
            f"({r['new_variant']}) | {r['speedup']:.1f}x | {1 / r['new_steps_per_s']:.4f} | "
            f"{r['old']['peak_memory_gib']:.2f} / {r['variants'][r['new_variant']]['peak_memory_gib']:.2f} | "
            f"{agree.get('loss_relative_difference', float('nan')):.1e} / "
            f"{agree.get('gradient_relative_difference', float('nan')):.1e} |")
    lines += ["", "Static variants (steps/s; warm-up s = compilation + capture):", ""]
    for r in report["rows"]:
        for name, v in r.get("variants", {}).items():
            text = f"{v['steps_per_s']:.2f} steps/s, warm-up {v['warmup_s']:.1f} s" if "steps_per_s" in v else v["error"]
            lines.append(f"- {r['setting']} batch {r['batch']}, {name}: {text}")
    lines += ["", "Single rollouts (B = 1, no gradients, bf16 on CUDA):", "",
              "| setting | vertices | reference ms/step | static ms/step | speedup | position RMS diff (m) |",
              "|---|---|---|---|---|---|"]
    for r in report.get("rollouts", []):
        if "error" in r:
            lines.append(f"| {r['setting']} | | {r['error'][:80]} | | | |")
            continue
        lines.append(f"| {r['setting']} | {r['vertices']} | {r['reference_ms_per_step']:.2f} | "
                     f"{r['static_ms_per_step']:.2f} | {r['speedup']:.1f}x | {r['position_rms_difference_m']:.1e} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--store", default="data/source/trajectories.zarr")
    parser.add_argument("--paper-params", default="params/gpu.yaml")
    parser.add_argument("--settings", default="default:8,default:32,paper:1")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--rollout-frames", type=int, default=25)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--tag", default="cpu")
    parser.add_argument("--budget-s", type=float, default=540.0)
    parser.add_argument("--out-dir", default="reports/gpu")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    device = torch.device(args.device)
    params = read_params(args.params, args.overrides)
    out = Path(args.out_dir) / f"train_speed_{args.tag}.json"
    report: dict[str, Any] = {"tag": args.tag, "steps": args.steps, "window": load_section(params, "train", TrainConfig).window,
                              "environment": environment_info(str(device)), "targets": TARGETS, "rows": [], "rollouts": []}
    if device.type == "cuda":
        report["environment"]["device_name"] = torch.cuda.get_device_name(device)
    tmp = Path(tempfile.mkdtemp(prefix="train_speed_"))
    stores = {"default": Path(args.store)}
    settings = [(name, int(batch)) for name, batch in (s.split(":") for s in args.settings.split(","))]
    rollout_done: set[str] = set()
    for name, batch in settings:
        row: dict[str, Any] = {"setting": name, "batch": batch}
        if time.perf_counter() - started > args.budget_s:
            row["skipped"] = f"over the {args.budget_s:.0f} s budget"
            report["rows"].append(row)
            continue
        try:
            p = params
            if name == "paper":
                from tests.synthetic_store import write_synthetic_store  # noqa: PLC0415 - only for this row
                p = read_params(args.paper_params)
                p["train"] = copy.deepcopy(params["train"])
                if name not in stores:
                    stores[name] = write_synthetic_store(tmp / "paper.zarr", p, [("fall", "train")],
                                                         frames=max(12, 2 * load_section(p, "train", TrainConfig).window))
            s = Setting(stores[name], p, batch, args.steps, device)
            row["vertices"] = s.layout.num_vertices
            row["agreement"] = first_batch_agreement(s)
            row["old"] = time_reference(s, bf16=True)
            row["variants"] = {}
            for variant in args.variants.split(","):
                try:
                    row["variants"][variant] = time_static(s, variant)
                except Exception as err:  # noqa: BLE001 - recorded; the next variant still runs
                    row["variants"][variant] = {"error": f"{type(err).__name__}: {err}"[:2000],
                                                "trace": traceback.format_exc()[-3000:]}
            timed = {k: v for k, v in row["variants"].items() if "steps_per_s" in v}
            best = max(timed, key=lambda k: timed[k]["steps_per_s"])
            row.update(old_steps_per_s=row["old"]["steps_per_s"], new_steps_per_s=timed[best]["steps_per_s"],
                       new_variant=best, speedup=timed[best]["steps_per_s"] / row["old"]["steps_per_s"])
            if name not in rollout_done:
                rollout_done.add(name)
                try:
                    report["rollouts"].append({"setting": name, "vertices": row["vertices"],
                                               **time_rollouts(s, args.rollout_frames)})
                except Exception as err:  # noqa: BLE001
                    report["rollouts"].append({"setting": name, "error": f"{type(err).__name__}: {err}"[:2000]})
        except Exception as err:  # noqa: BLE001 - a failed setting is recorded, the others still run
            row["error"] = f"{type(err).__name__}: {err}"[:2000]
            row["trace"] = traceback.format_exc()[-3000:]
        report["rows"].append(row)
        report["wall_s"] = time.perf_counter() - started
        write_report_atomic(out, report, markdown(report))
        print(markdown(report), flush=True)


if __name__ == "__main__":
    main()
