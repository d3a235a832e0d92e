"""Host cost of the source data's acceptance checks per episode (wc.validate.predicates), per check, at the
params' bag size and at paper size, on the self-intersection check's warp devices.

    python -m benchmarks.check_cost [--params params.yaml] [--set key=value ...] [--vertices 300,20274]
        [--frames 150] [--devices cpu,cuda] [--repeats 3] --out reports/check_cost_<tag>.json

Simulate and expand judge every episode with these checks after each batch, on the host, one episode after
another: at paper size they can cost more than the GPU simulation of the batch itself. The episode is the
bag's rest mesh, jittered by 0.1 mm per frame, with the robot at its home posture (no check fails, so each runs
over every frame). Timed: the median of `--repeats` runs after one warm-up (kernel compile). Writes the JSON
and a Markdown table beside it.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp

from wc.config import add_params_arguments, load_section, read_params
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene
from wc.validate.config import ValidateConfig
from wc.validate.predicates import PREDICATES, Episode

PAPER_VERTICES = 20274


def jittered_episode(scene: Any, frames: int, seed: int = 0) -> Episode:
    """`frames` frames of the objects at rest, jittered by 0.1 mm, the robot at home (action zeros)."""
    rest = np.concatenate([m.vertices for m in scene.objects.values()])
    x = (rest[None] + 1e-4 * np.random.default_rng(seed).standard_normal((frames, *rest.shape))).astype(np.float32)
    action = np.zeros((frames, 14), np.float32)
    return Episode(x, np.zeros_like(x), action, scene.link_poses(action), 0.04)


def time_checks(scene: Any, ep: Episode, cfg: ValidateConfig, repeats: int) -> dict[str, float]:
    """Median seconds of each check over the episode (after a warm-up run)."""
    out = {}
    for name, check in PREDICATES.items():
        check(scene, ep, cfg)
        runs = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            check(scene, ep, cfg)
            if cfg.device != "cpu":
                wp.synchronize()
            runs.append(time.perf_counter() - t0)
        out[name] = statistics.median(runs)
    return out


def markdown(rows: list[dict[str, Any]]) -> str:
    names = list(PREDICATES)
    lines = ["| vertices | device | " + " | ".join(names) + " | total s / episode |",
             "|---" * (len(names) + 3) + "|"]
    for r in rows:
        cells = " | ".join(f"{r['seconds'][n]:.3f}" for n in names)
        lines.append(f"| {r['vertices']} | {r['device']} | {cells} | {r['total_s']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--vertices", default="", help="bag target vertices, comma-separated (default: params', paper)")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--devices", default="cpu,cuda", help="self-intersection devices; cuda skipped without one")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="reports/check_cost.json")
    args = parser.parse_args(argv)
    params = read_params(args.params, args.overrides)
    own = params["scene"]["bag"]["target_vertices"]
    vertices = [int(v) for v in args.vertices.split(",")] if args.vertices else list(dict.fromkeys([own, PAPER_VERTICES]))
    devices = [d for d in args.devices.split(",") if d == "cpu" or wp.is_cuda_available()]
    base_cfg = load_section(params, "validate", ValidateConfig)
    rows = []
    for n in vertices:
        params["scene"]["bag"]["target_vertices"] = n
        scene = build_scene(load_section(params, "scene", SceneConfig))
        ep = jittered_episode(scene, args.frames)
        for device in devices:
            seconds = time_checks(scene, ep, dataclasses.replace(base_cfg, device=device), args.repeats)
            rows.append({"vertices": int(ep.x.shape[1]), "target_vertices": n, "device": device, "seconds": seconds,
                         "total_s": sum(seconds.values())})
            print(f"{ep.x.shape[1]} vertices, self-intersection on {device}: {rows[-1]['total_s']:.2f} s / episode")
    report = {"frames": args.frames, "repeats": args.repeats, "rows": rows,
              "environment": environment_info("cuda" if "cuda" in devices else "cpu")}
    out = Path(args.out)
    write_json_atomic(out, report)
    out.with_suffix(".md").write_text(f"Acceptance checks per {args.frames}-frame episode (s, median of "
                                      f"{args.repeats})\n\n" + markdown(rows))


if __name__ == "__main__":
    main()
