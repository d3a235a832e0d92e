"""How far the bag's membrane stretches while the robot lifts it, per material / solver setting.

    python -m benchmarks.fabric_stretch --params params.yaml [--set key=value ...] [--task lift_handle] [--plans 16]
        [--settings "sim.bag.tri_ke=1000.0" "sim.bag.tri_ke=10000.0,sim.bag.tri_ka=10000.0" ...]
        [--p99-limit 0.05] [--max-limit 0.15] [--seed 0]
        --out reports/fabric_stretch_<tag>.json      (also writes the .md table and a .png chart)

A setting is a comma-separated list of overrides applied on top of `--set`. The same episode specs (drawn once from
the base params, as the simulate stage draws them, agent seed `--seed`) are reset, settled and planned under each
setting, rolled out in Newton (`sim.worlds` at a time, timed) and judged by the source data's checks and the task's
own verdict (lift_handle: accepted, or not_lifted when the strap slipped out of the pads). Strain is length / rest - 1
of the bag's rest edges (wc.validate.edge_stretch), over two frame sets: the lifted frames (the bag's lowest vertex at
least the task's `success_lift_m` above the table) and all frames; a frame set holds an episode's frames before its
first non-finite one (after a blow-up too, so its strains show in the maxima). Percentiles pool the (frame, edge) samples of every episode; `handles` are the edges of the
two straps (shared rim vertices included). A setting meets the targets when, over the lifted frames, p99 <= --p99-limit
and the worst edge <= --max-limit; whether the pads still hold the bag is the accepted share beside it. Rows are
written as they finish, so a run cut short keeps them; a blow-up is a verdict like any other.
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.newton_convergence import draw_specs
from wc.agent.replay import Plan, Replay, plan_specs, replay, share
from wc.agent.runner import TaskWorld, build_task_world
from wc.config import add_params_arguments, load_section, read_params
from wc.devices import resolve_warp_device
from wc.reports import cell, environment_info, pyplot, save_figure_atomic, write_report_atomic
from wc.scene.config import SceneConfig
from wc.sim.config import SimConfig
from wc.tasks.bag_geometry import lowest_height
from wc.tasks.base import EpisodeSpec, get_task
from wc.validate.config import ValidateConfig
from wc.validate.edge_stretch import RestEdges, group_edges, stretch_summary

FRAME_SETS = ("lifted", "all_frames")


def parse_setting(text: str) -> list[str]:
    """'a.b=1,c.d=[1, 2]' -> ['a.b=1', 'c.d=[1, 2]']: split at the commas that start another key=value."""
    items = [t.strip() for t in re.split(r",(?=\s*[A-Za-z_][\w.]*=)", text) if t.strip()]
    bad = [t for t in items if not re.match(r"[A-Za-z_][\w.]*=", t)]
    if bad:
        raise argparse.ArgumentTypeError(f"a setting is key=value[,key=value ...], got {text!r}")
    return items


def finite_prefix(x: np.ndarray) -> int:
    """Frames of x (T, N, 3) before its first non-finite one."""
    bad = np.flatnonzero(~np.isfinite(x).all(axis=(1, 2)))
    return int(bad[0]) if len(bad) else len(x)


class BagStretch:
    """The bag's rest edges in a task world and the strains of its replays, pooled per frame set and edge subset."""

    def __init__(self, world: TaskWorld) -> None:
        scene = world.scene
        if "bag" not in scene.objects:
            raise ValueError(f"fabric stretch: task {world.task.name} has no bag (objects {list(scene.objects)})")
        bag = scene.objects["bag"]
        self.scene, self.rows = scene, scene.vertex_slices()["bag"]
        self.edges = RestEdges.of_mesh(bag.vertices, bag.faces)
        straps = [bag.groups[g] for g in ("handle_0", "handle_1") if g in bag.groups]
        self.subsets = {"all": np.ones(len(self.edges.edges), bool)}
        if straps:
            self.subsets["handles"] = group_edges(self.edges.edges, np.concatenate(straps))
        self.lift_m = getattr(world.task.cfg, "success_lift_m", None)
        self.pooled: dict[str, dict[str, list[np.ndarray]]] = {f: {s: [] for s in self.subsets} for f in FRAME_SETS}

    def add(self, x: np.ndarray) -> dict[str, Any]:
        """Pool one replay's strains (x (T, V, 3), every object of the scene); its frame counts and worst edges."""
        frames = finite_prefix(x)
        strain = self.edges.strains(x[:frames, self.rows]).astype(np.float32)
        lifted = (np.zeros(frames, bool) if self.lift_m is None
                  else lowest_height(self.scene, x[:frames]) >= self.lift_m)
        chosen = {"lifted": strain[lifted], "all_frames": strain}
        for frame_set, s in chosen.items():
            for name, mask in self.subsets.items():
                self.pooled[frame_set][name].append(s[:, mask])
        return {"frames": len(x), "finite_frames": frames, "lifted_frames": int(lifted.sum()),
                **{f"worst_edge_{f}": float(s.max()) if s.size else None for f, s in chosen.items()}}

    def summaries(self, limit: float) -> dict[str, dict[str, dict[str, float | int] | None]]:
        """Per frame set and edge subset, `stretch_summary` of the pooled strains."""
        return {f: {name: stretch_summary(np.concatenate([a.ravel() for a in parts]) if parts else np.zeros(0), limit)
                    for name, parts in subsets.items()} for f, subsets in self.pooled.items()}


def worst_edges(episodes: list[dict[str, Any]]) -> dict[str, dict[str, float | int | None]]:
    """Per frame set, the median and max over episodes of each episode's worst edge strain."""
    out = {}
    for f in FRAME_SETS:
        worst = [e[f"worst_edge_{f}"] for e in episodes if e[f"worst_edge_{f}"] is not None]
        out[f] = {"episodes": len(worst), "median": statistics.median(worst) if worst else None,
                  "max": max(worst) if worst else None}
    return out


def replay_batches(world: TaskWorld, plans: list[Plan], validate_cfg: ValidateConfig, frame_dt_s: float,
                   perturb_m: float = 0.0, seed: int = 0, desc: str = "newton replay"
                   ) -> Iterator[tuple[list[Plan], list[Replay], float]]:
    """wc.agent.replay.replay one `sim.worlds` batch at a time, positions kept, so that a caller reducing them holds
    one batch's: per batch its plans, their replays and the seconds the replay took (batch k's noise seeded seed + k)."""
    for k, first in enumerate(range(0, len(plans), world.sim.worlds)):
        batch = plans[first:first + world.sim.worlds]
        started = time.perf_counter()
        replays = replay(world, batch, validate_cfg, frame_dt_s, perturb_m, seed + k, desc=desc)
        yield batch, replays, time.perf_counter() - started


def measure(params: dict[str, Any], task_name: str, specs: list[EpisodeSpec], setting: list[str],
            limits: tuple[float, float]) -> dict[str, Any]:
    """One setting's row: plans, verdicts, stretch summaries and timings."""
    sim_cfg, validate_cfg = load_section(params, "sim", SimConfig), load_section(params, "validate", ValidateConfig)
    world = build_task_world(load_section(params, "scene", SceneConfig), sim_cfg, get_task(task_name, params))
    started = time.perf_counter()
    plans = plan_specs(world, specs, sim_cfg.worlds)
    reset_s = time.perf_counter() - started
    label = ",".join(setting) or "base"
    row: dict[str, Any] = {"setting": label, "overrides": setting, "iterations": sim_cfg.iterations,
                           "substeps": sim_cfg.substeps, "worlds": sim_cfg.worlds, "tri_ke": sim_cfg.bag.tri_ke,
                           "tri_ka": sim_cfg.bag.tri_ka, "bag_vertices": len(world.scene.objects["bag"].vertices),
                           "plans": len(plans), "unplannable": len(specs) - len(plans),
                           "reset_s": reset_s}
    if not plans:
        return row | {"verdicts": {}, "accepted": None, "episodes": []}
    stretch, episodes, verdicts, rollout_s = BagStretch(world), [], [], 0.0
    for batch, replays, seconds in replay_batches(world, plans, validate_cfg, sim_cfg.frame_dt_s, desc=label):
        rollout_s += seconds
        for plan, r in zip(batch, replays):
            verdicts.append(r.verdict)
            episodes.append({"seed": plan.spec.seed, "verdict": r.verdict, "failure_frame": r.failure_frame,
                             "detail": r.detail, **stretch.add(r.x)})
    summaries = stretch.summaries(limits[0])
    lifted, worst = summaries["lifted"]["all"], worst_edges(episodes)
    return row | {
        "verdicts": dict(Counter(verdicts)), "accepted": share([v == "accepted" for v in verdicts]),
        "lifted_above_m": stretch.lift_m,
        "episodes_lifted": sum(e["lifted_frames"] > 0 for e in episodes),
        "stretch": summaries, "worst_edge": worst,
        "meets_targets": lifted is not None and lifted["p99"] <= limits[0] and lifted["max"] <= limits[1],
        "rollout_s": rollout_s, "rollout_s_per_episode": rollout_s / len(plans),
        "frames_per_episode": sum(len(p.action) for p in plans) / len(plans), "episodes": episodes}


def _pct(value: float | None) -> str:
    return cell(value, scale=100)


def markdown(report: dict[str, Any]) -> str:
    env, (p99_limit, max_limit) = report["environment"], report["limits"]
    lines = [f"# Bag membrane stretch: {report['task']}, {report['plans']} plans per setting", "",
             f"Device {env['device']} ({env.get('gpu', env['cpu'])}), warp {env['warp']}, newton {env['newton']}; "
             f"params {report['params']} {' '.join(report['overrides'])}; agent seed {report['seed']}.",
             "Strain = edge length / rest length - 1 [%], pooled over the (frame, edge) samples of every episode; "
             "lifted: frames whose lowest bag vertex is at least the task's success height above the table. "
             f"Targets over the lifted frames: p99 <= {p99_limit * 100:g} %, worst edge <= {max_limit * 100:g} %.", "",
             "| setting | bag vertices | iterations | plans | accepted | verdicts | lifted frames | p50 / p90 / p99 / max lifted "
             f"| > {p99_limit * 100:g} % lifted | handles p99 / max lifted | p99 / max all frames "
             "| worst edge per episode, median / max (lifted) | meets | rollout s per episode |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["settings"]:
        if not r["plans"]:
            lines.append(f"| {r['setting']} | {r.get('bag_vertices', '-')} | {r['iterations']} | 0 | - | - | - | - | - | - "
                         "| - | - | - | - |")
            continue
        lifted, every = r["stretch"]["lifted"], r["stretch"]["all_frames"]
        a, h, w = lifted["all"] or {}, lifted.get("handles") or {}, r["worst_edge"]["lifted"]
        verdicts = ", ".join(f"{k} {n}" for k, n in sorted(r["verdicts"].items()))
        lifted_frames = sum(e["lifted_frames"] for e in r["episodes"])
        lines.append(
            f"| {r['setting']} | {r.get('bag_vertices', '-')} | {r['iterations']} | {r['plans']} | {r['accepted']:.2f} | {verdicts} | {lifted_frames} "
            f"| {' / '.join(_pct(a.get(k)) for k in ('p50', 'p90', 'p99', 'max'))} "
            f"| {_pct(a.get('share_above_limit'))} | {_pct(h.get('p99'))} / {_pct(h.get('max'))} "
            f"| {_pct(every['all']['p99'])} / {_pct(every['all']['max'])} | {_pct(w['median'])} / {_pct(w['max'])} "
            f"| {'yes' if r['meets_targets'] else 'no'} | {r['rollout_s_per_episode']:.1f} |")
    return "\n".join(lines) + "\n"


def tick_label(setting: str, width: int = 22) -> str:
    """A setting as an axis label: one override per line, each key by its last two parts (sim.bag.tri_ke=1e4 ->
    bag.tri_ke=1e4); an override longer than `width` characters puts its value on a line of its own."""
    head = setting.split(" (")[0]
    lines = []
    for override in parse_setting(head) if "=" in head else [head]:
        key, _, value = override.partition("=")
        short = ".".join(key.split(".")[-2:])
        lines.append(override if not value else f"{short}={value}" if len(short) + len(value) < width
                     else f"{short}\n={value}")
    note = setting[len(head):].strip()
    return "\n".join(lines + ([note] if note else []))


def chart(report: dict[str, Any], path: Path) -> None:
    """Per setting, p99 and worst-edge strain over the lifted frames (all edges and the handles; all frames faint),
    the targets as horizontal lines, the accepted share written above each setting."""
    plt = pyplot()
    rows = [r for r in report["settings"] if r["plans"]]
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(rows) + 2), 4.5))
    at = np.arange(len(rows))

    def values(frame_set: str, subset: str, key: str) -> list[float]:
        found = [(r["stretch"][frame_set].get(subset) or {}).get(key) for r in rows]
        return [np.nan if v is None else v * 100 for v in found]

    series = [(f, subset, key, style, colour, alpha)
              for f, subset, style, alpha in (("lifted", "all", "o", 1.0), ("lifted", "handles", "s", 1.0),
                                              ("all_frames", "all", "x", 0.5))
              for key, colour in (("p99", "tab:blue"), ("max", "tab:red"))]
    bottom, top = 0.0, 25.0
    for k, (frame_set, subset, key, style, colour, alpha) in enumerate(series):
        y = values(frame_set, subset, key)
        shown = [v for v in y if np.isfinite(v)]
        bottom, top = min([bottom, *shown]), max([top, *shown])
        ax.plot(at + 0.4 * (k / (len(series) - 1) - 0.5), y, style, color=colour, alpha=alpha, linestyle="none",
                label=f"{key}, {subset} edges, {frame_set.replace('_', ' ')}")
    for limit, name in zip(report["limits"], ("p99 target", "worst-edge target")):
        ax.axhline(limit * 100, color="grey", linestyle="--", linewidth=1)
        ax.annotate(name, (-0.5, limit * 100), textcoords="offset points", xytext=(2, 2), fontsize=8, color="grey")
    for k, r in enumerate(rows):
        ax.annotate(f"accepted {r['accepted']:.2f}", (k, 1.0), xycoords=("data", "axes fraction"),
                    textcoords="offset points", xytext=(0, -12), ha="center", fontsize=8)
    ax.set_yscale("symlog", linthresh=20.0)  # percent: linear to 20 %, logarithmic beyond (blow-ups)
    ax.set_ylim(bottom, top * 2.0)
    ax.set_yticks([t for t in (0, 5, 10, 15, 20, 50, *(10.0 ** np.arange(2, 9))) if bottom <= t <= top * 2.0])
    ax.yaxis.set_major_formatter(lambda v, _: f"{v:g}")
    ax.set_xticks(at, [tick_label(r["setting"]) for r in rows], fontsize=7)
    ax.set_xlim(-0.5, len(rows) - 0.5)
    ax.set_ylabel("edge strain [%]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.suptitle(f"Bag membrane stretch: {report['task']}, {report['plans']} plans per setting "
                 f"({report['environment']['device']})")
    fig.tight_layout()
    save_figure_atomic(fig, path)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--task", default="lift_handle")
    parser.add_argument("--plans", type=int, default=16, help="episode specs per setting")
    parser.add_argument("--settings", type=parse_setting, nargs="+", default=[[]],
                        help="one or more settings, each key=value[,key=value ...] on top of --set (default: --set "
                             "alone)")
    parser.add_argument("--p99-limit", type=float, default=0.05, help="target p99 strain over the lifted frames")
    parser.add_argument("--max-limit", type=float, default=0.15, help="target worst-edge strain over the lifted frames")
    parser.add_argument("--seed", type=int, default=0, help="agent seed of the specs")
    parser.add_argument("--out", default="reports/fabric_stretch.json")
    args = parser.parse_args(argv)
    if args.plans < 1 or not 0 < args.p99_limit <= args.max_limit:
        parser.error(f"--plans must be >= 1 and 0 < --p99-limit <= --max-limit, got {args.plans}, "
                     f"{args.p99_limit}, {args.max_limit}")

    base = read_params(args.params, args.overrides)
    settings = [(s, read_params(args.params, [*args.overrides, *s])) for s in args.settings]  # a bad key fails now
    specs = draw_specs(base, args.task, args.plans, args.seed)
    out = Path(args.out)
    report: dict[str, Any] = {
        "benchmark": "fabric_stretch",
        "what": f"bag edge strain (length / rest - 1) of {args.plans} {args.task} specs replayed in Newton under each "
                "setting, over the lifted frames and all frames, beside the task's verdicts",
        "task": args.task, "plans": args.plans, "command": " ".join(sys.argv), "params": args.params,
        "overrides": args.overrides, "seed": args.seed, "limits": [args.p99_limit, args.max_limit],
        "environment": environment_info(resolve_warp_device(base["sim"]["device"], "sim.device")), "settings": [],
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    for setting, params in settings:
        row = measure(params, args.task, specs, setting, (args.p99_limit, args.max_limit))
        report["settings"].append(row)
        lifted = (row.get("stretch") or {}).get("lifted", {}).get("all") or {}
        print(f"{row['setting']}: accepted {row['accepted']}, verdicts {row['verdicts']}, lifted p99 "
              f"{_pct(lifted.get('p99'))} %, max {_pct(lifted.get('max'))} %; "
              f"{row.get('rollout_s_per_episode', float('nan')):.1f} s per episode", flush=True)
        write_report_atomic(out, report, markdown(report))
        chart(report, out.with_suffix(".png"))
    print(markdown(report))


if __name__ == "__main__":
    main()
