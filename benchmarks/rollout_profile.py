"""Where one WorldContact rollout step spends its time: per-part wall time, timed with device events.

    python -m benchmarks.rollout_profile --params params/gpu.yaml --store STORE [--frames 10] [--batch 1]
        --out reports/rollout_profile_<tag>.json   (+ .md)

Parts: prescribed samples (`boundary_samples`), the tokenizer's neighbour searches (`search_pairs`: the
Verlet-skin reuse test plus any fresh `radius_pairs` search, timed also on its own; `nearest_index`), the rest of the tokenizer (continuous convolutions), each encoder level (attention +
merge), each decoder layer, the head. Hooks record an event pair around each part (CUDA events on a GPU,
clock reads on CPU) over a no-gradient rollout of the store's first episode; the medians over steps are
reported beside the whole step, with and without bf16 autocast. The rollout code is the model's own: the
hooks only read clocks.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch

import wc.model.layout as layout_module
import wc.model.neighbor_cache as neighbor_cache_module
import wc.model.tokenizer as tokenizer_module
from wc.config import add_params_arguments, load_section, read_params
from wc.data.store import TrajectoryStore
from wc.model.config import ModelConfig
from wc.model.rollout import rollout
from wc.reports import environment_info, write_report_atomic
from wc.train.data import data_scales, episode_phases, read_phase_window
from wc.model.layout import scene_layout
from wc.model.worldcontact import WorldContact


class PartTimer:
    """Event pairs per named part; `ms()` synchronises once and returns the summed milliseconds per part per step."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.pairs: dict[str, list[tuple[Any, Any]]] = defaultdict(list)

    def _mark(self) -> Any:
        if self.device.type == "cuda":
            event = torch.cuda.Event(enable_timing=True)
            event.record()
            return event
        return time.perf_counter()

    @contextmanager
    def part(self, name: str) -> Iterator[None]:
        start = self._mark()
        yield
        self.pairs[name].append((start, self._mark()))

    def ms(self) -> dict[str, float]:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            return {k: sum(a.elapsed_time(b) for a, b in v) for k, v in self.pairs.items()}
        return {k: 1e3 * sum(b - a for a, b in v) for k, v in self.pairs.items()}


def _wrap(timer_ref: list[PartTimer | None], name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    def timed(*args: Any, **kwargs: Any) -> Any:
        timer = timer_ref[0]
        if timer is None:
            return fn(*args, **kwargs)
        with timer.part(name):
            return fn(*args, **kwargs)
    return timed


def _instrument(model: WorldContact, timer_ref: list[PartTimer | None]) -> None:
    """Time the model's parts through forward hooks and wrappers of the module-level search functions."""
    parts = {"tokenizer (incl. neighbour search)": model.tokenizer, "head": model.head}
    parts.update({f"encoder level {i}": level for i, level in enumerate(model.encoder.levels)})
    parts.update({f"decoder layer {i}": layer for i, layer in enumerate(model.decoder.layers)})
    for name, module in parts.items():
        module.forward = _wrap(timer_ref, name, module.forward)
    tokenizer_module.search_pairs = _wrap(timer_ref, "neighbour search (incl. reuse test)", tokenizer_module.search_pairs)
    tokenizer_module.nearest_index = _wrap(timer_ref, "neighbour search: nearest_index", tokenizer_module.nearest_index)
    neighbor_cache_module.radius_pairs = _wrap(timer_ref, "neighbour search: radius_pairs (fresh search)",
                                               neighbor_cache_module.radius_pairs)
    import wc.model.rollout as rollout_module
    rollout_module.boundary_samples = _wrap(timer_ref, "prescribed samples", layout_module.boundary_samples)


@torch.no_grad()
def profile(store: TrajectoryStore, model_cfg: ModelConfig, frames: int, batch: int, autocast: bool,
            device: torch.device) -> dict[str, Any]:
    """Median per-step milliseconds of each part, and of the whole step, over a `frames`-step rollout."""
    phase = episode_phases(store, store.episode_ids[0])[0]
    scales = data_scales(store, [phase], 1)
    model = WorldContact(model_cfg, scales.velocity_m_s, scales.delta_x_m, scales.delta_v_m_s).to(device).eval()
    layout = scene_layout(store, list(phase.layout[0]), list(phase.layout[1]), model_cfg.tag_scale).to(device)
    frames = min(frames, phase.stop - 1)
    a = {n: torch.from_numpy(arr).to(device) for n, arr in read_phase_window(store, phase, 0, frames + 1).items()}
    x = a["x"][0].expand(batch, -1, -1).contiguous()
    v = a["v"][0].expand(batch, -1, -1).contiguous()
    poses = a["poses"][None].expand(batch, -1, -1, -1).contiguous()
    timer_ref: list[PartTimer | None] = [None]
    _instrument(model, timer_ref)
    per_step: dict[str, list[float]] = defaultdict(list)
    with torch.autocast("cuda", dtype=torch.bfloat16, enabled=autocast and device.type == "cuda"):
        rollout(model, layout, x, v, poses[:, :2], store.dt)  # warm-up: allocations, kernel caches
        for t in range(frames):
            timer_ref[0] = PartTimer(device)
            with timer_ref[0].part("whole step"):
                rollout(model, layout, x, v, poses[:, t:t + 2], store.dt)
            for name, ms in timer_ref[0].ms().items():
                per_step[name].append(ms)
            timer_ref[0] = None
    medians = {name: statistics.median(ms) for name, ms in per_step.items()}
    return {"batch": batch, "frames": frames, "autocast_bf16": autocast, "compress": model_cfg.compress,
            "vertices": int(x.shape[1]), "ms_per_step_median": medians}


def markdown(report: dict[str, Any]) -> str:
    env = report["environment"]
    lines = [f"# One WorldContact rollout step, part by part ({report['runs'][0]['vertices']:,} predicted vertices)", "",
             f"Device {env['device']} ({env.get('gpu', env['cpu'])}), torch {env['torch']}; params {report['params']}. "
             "Median milliseconds per step; parts nest (the tokenizer includes its neighbour searches), so they "
             "do not sum to the whole step.", ""]
    for run in report["runs"]:
        whole = run["ms_per_step_median"]["whole step"]
        lines += [f"## batch {run['batch']}, bf16 {'on' if run['autocast_bf16'] else 'off'}: "
                  f"{whole:.1f} ms per step", "", "| part | ms | share of step |", "|---|---|---|"]
        for name, ms in sorted(run["ms_per_step_median"].items(), key=lambda kv: -kv[1]):
            lines.append(f"| {name} | {ms:.2f} | {100 * ms / whole:.0f} % |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--store", required=True, help="trajectory store whose first episode is rolled out")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--device", default=None, help="default: the train section's device")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    params = read_params(args.params, args.overrides)
    model_cfg = load_section(params, "model", ModelConfig)
    device = torch.device(args.device or params["train"]["device"])
    store = TrajectoryStore(args.store)
    report: dict[str, Any] = {"params": args.params, "store": args.store,
                              "environment": environment_info(str(device)), "runs": []}
    for autocast in ((False, True) if device.type == "cuda" else (False,)):
        report["runs"].append(profile(store, model_cfg, args.frames, args.batch, autocast, device))
        print(report["runs"][-1], flush=True)
    out = Path(args.out)
    write_report_atomic(out, report, markdown(report))
    print(markdown(report))


if __name__ == "__main__":
    main()
