"""How reproducible the source simulator is against what it costs: VBD iterations per substep swept on the same plans.

    python -m benchmarks.newton_convergence --params params.yaml [--set key=value ...] [--task lift_handle]
        [--iterations 5,10,20] [--plans 64] [--perturb-m 0 0.0003] [--seed 0]
        --out reports/newton_convergence_<tag>.json      (also writes the .md table and a .png chart)

For each iteration count the same episode specs (drawn as the simulate stage draws them, agent seed `--seed`) are
reset, settled and planned, rolled out once in Newton (`sim.worlds` at a time, timed) and judged by the source data's
checks; then replayed once per `--perturb-m` scale in another batch order from frame-0 positions + N(0, scale^2)
(wc/agent/replay.py). A row gives Newton's verdict agreement with its own first rollout, the mean RMS distance
between the two, the accepted share, the verdict agreement with the most-iterated setting on the plans both ran, and
the wall seconds per episode: the chart puts the agreement against the cost. The teacher check scores a model against
one Newton rollout, so a setting whose re-run agrees on only 0.7 of the plans caps any model at about that. Rows are
written as they finish, so a run cut short keeps them.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

from wc.agent.planner import CoveragePlanner
from wc.agent.replay import plan_specs, replay, same_verdict, self_agreement, share
from wc.agent.runner import build_task_world
from wc.devices import resolve_warp_device
from wc.config import add_params_arguments, load_section, read_params
from wc.reports import environment_info, pyplot, save_figure_atomic, write_report_atomic
from wc.scene.config import SceneConfig
from wc.seeds import episode_seed
from wc.sim.config import SimConfig
from wc.tasks.base import EpisodeSpec, get_task
from wc.validate.config import ValidateConfig


def _ints(text: str) -> list[int]:
    values = [int(t) for t in text.split(",") if t.strip()]
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers separated by commas, got {text!r}")
    return values


def draw_specs(params: dict[str, Any], task_name: str, count: int, seed: int) -> list[EpisodeSpec]:
    """The first `count` specs the simulate stage's coverage planner would propose for the task."""
    task, planner = get_task(task_name, params), CoveragePlanner()
    return [planner.propose(task, episode_seed(seed, 0, i)) for i in range(count)]


def measure(params: dict[str, Any], task_name: str, specs: list[EpisodeSpec], scales_m: list[float],
            seed: int) -> tuple[dict[str, Any], dict[int, str]]:
    """One setting's row, and the first rollout's verdict per spec seed."""
    sim_cfg, validate_cfg = load_section(params, "sim", SimConfig), load_section(params, "validate", ValidateConfig)
    world = build_task_world(load_section(params, "scene", SceneConfig), sim_cfg, get_task(task_name, params))
    started = time.perf_counter()
    plans = plan_specs(world, specs, sim_cfg.worlds)
    reset_s = time.perf_counter() - started
    if not plans:
        raise RuntimeError(f"newton convergence: none of {len(specs)} {task_name} specs could be planned")
    started = time.perf_counter()
    first = replay(world, plans, validate_cfg, sim_cfg.frame_dt_s, desc=f"{sim_cfg.iterations} iterations")
    rollout_s = time.perf_counter() - started
    agreement, _ = self_agreement(world, plans, first, validate_cfg, sim_cfg.frame_dt_s, scales_m, seed)
    row = {"iterations": sim_cfg.iterations, "substeps": sim_cfg.substeps, "worlds": sim_cfg.worlds,
           "plans": len(plans), "unplannable": len(specs) - len(plans),
           "accepted": share([r.verdict == "accepted" for r in first]),
           "verdicts": dict(Counter(r.verdict for r in first)),
           "failures_by": dict(Counter(f"{r.verdict} ({r.detail.get('body') or r.detail.get('criterion')})"
                                       for r in first if r.detail)),
           "self_agreement": agreement, "reset_s": reset_s, "rollout_s": rollout_s,
           "rollout_s_per_episode": rollout_s / len(plans),
           "frames_per_episode": sum(len(p.action) for p in plans) / len(plans)}
    return row, {p.spec.seed: r.verdict for p, r in zip(plans, first)}


def agreement_with_most_iterated(rows: list[dict[str, Any]], verdicts: list[dict[int, str]]) -> None:
    """Each row's verdict agreement with the most-iterated row's, on the specs both planned (set in place)."""
    best = max(range(len(rows)), key=lambda i: rows[i]["iterations"])
    for row, mine in zip(rows, verdicts):
        shared = [s for s in mine if s in verdicts[best]]
        row["agreement_with_most_iterated"] = share([same_verdict(mine[s], verdicts[best][s]) for s in shared])
        row["most_iterated"] = rows[best]["iterations"]


def _flips(row: dict[str, Any]) -> str:
    """The verdict changes of a row's re-runs, summed ('-' for reports written before they were recorded)."""
    if not any("flipped" in again for again in row["self_agreement"]):
        return "-"
    flips: Counter[str] = Counter()
    for again in row["self_agreement"]:
        flips.update(again["flipped"])
    return ", ".join(f"{k} {n}" for k, n in sorted(flips.items())) or "none"


def markdown(report: dict[str, Any]) -> str:
    env = report["environment"]
    scales = report["perturb_m"]
    lines = [f"# Newton against itself: {report['task']}, VBD iterations per substep", "",
             f"Device {env['device']} ({env.get('gpu', env['cpu'])}), warp {env['warp']}, newton {env['newton']}; "
             f"params {report['params']} {' '.join(report['overrides'])}; agent seed {report['seed']}.",
             "Agreement: share of plans whose verdict (accepted, or rejected for any reason) equals that of Newton's "
             "first rollout when replayed in another batch order from frame-0 positions + N(0, s^2); RMS: mean "
             "over the episode of the RMS vertex distance between the two.", "",
             "| iterations | substeps | plans | accepted | " + " | ".join(
                 f"agreement / RMS mm, s = {s:g} m" for s in scales)
             + " | agrees with most iterated | rollout s per episode | flips (first -> re-run) |",
             "|---|---|---|---|" + "---|" * len(scales) + "---|---|---|"]
    for r in report["settings"]:
        cells = [f"{a['agreement']:.2f} / {a['mean_rms_to_first_m'] * 1e3:.1f}" for a in r["self_agreement"]]
        most = r.get("agreement_with_most_iterated")
        lines.append(f"| {r['iterations']} | {r['substeps']} | {r['plans']} | {r['accepted']:.2f} | "
                     + " | ".join(cells) + f" | {'-' if most is None else f'{most:.2f}'} "
                     f"| {r['rollout_s_per_episode']:.2f} | {_flips(r)} |")
    return "\n".join(lines) + "\n"


def chart(report: dict[str, Any], path: Path) -> None:
    """Against rollout seconds per episode, one point per setting (in order of cost): Newton's verdict agreement with
    its first rollout and the mean RMS distance to it, one line per noise scale."""
    plt = pyplot()
    rows = sorted(report["settings"], key=lambda r: r["rollout_s_per_episode"])
    cost = [r["rollout_s_per_episode"] for r in rows]
    fig, (agree, drift) = plt.subplots(1, 2, figsize=(10, 4))
    for k, scale in enumerate(report["perturb_m"]):
        label = f"re-run {k + 1}, frame-0 noise {scale:g} m"
        agree.plot(cost, [r["self_agreement"][k]["agreement"] for r in rows], "o-", label=label)
        drift.plot(cost, [r["self_agreement"][k]["mean_rms_to_first_m"] * 1e3 for r in rows], "o-", label=label)
    for r, c in zip(rows, cost):
        for ax, y in ((agree, r["self_agreement"][0]["agreement"]),
                      (drift, r["self_agreement"][0]["mean_rms_to_first_m"] * 1e3)):
            ax.annotate(f"{r['iterations']} it", (c, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    agree.set_ylabel("verdict agreement with the first rollout")
    agree.set_ylim(0, 1.05)
    drift.set_ylabel("mean RMS distance to the first rollout [mm]")
    drift.set_ylim(bottom=0)
    for ax in (agree, drift):
        ax.set_xlabel(f"Newton rollout wall s per episode ({report['environment']['device']})")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"Newton against itself: {report['task']}, {rows[0]['plans']} plans, VBD iterations per substep")
    fig.tight_layout()
    save_figure_atomic(fig, path)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_params_arguments(parser)
    parser.add_argument("--task", default="lift_handle")
    parser.add_argument("--iterations", type=_ints, default=[5, 10, 20], help="VBD iterations per substep, e.g. 5,10,20")
    parser.add_argument("--plans", type=int, default=64, help="episode specs per setting")
    parser.add_argument("--perturb-m", type=float, nargs="+", default=[0.0, 0.0003],
                        help="frame-0 noise scales of the re-runs [m] (0: another batch order only)")
    parser.add_argument("--seed", type=int, default=0, help="agent seed of the specs; also seeds the re-runs")
    parser.add_argument("--out", default="reports/newton_convergence.json")
    args = parser.parse_args(argv)
    if args.plans < 1 or any(not s >= 0 for s in args.perturb_m):
        parser.error(f"--plans must be >= 1 and --perturb-m scales >= 0, got {args.plans}, {args.perturb_m}")

    base = read_params(args.params, args.overrides)
    specs = draw_specs(base, args.task, args.plans, args.seed)
    out = Path(args.out)
    report: dict[str, Any] = {
        "benchmark": "newton_convergence",
        "what": f"Newton against itself: {args.plans} {args.task} specs at VBD iterations {args.iterations}, each rolled "
                f"out, then re-run in another batch order from frame-0 noise {args.perturb_m} m; verdict agreement and "
                "RMS distance to the first rollout against rollout s per episode",
        "task": args.task, "command": " ".join(sys.argv), "params": args.params,
        "overrides": args.overrides, "seed": args.seed, "perturb_m": args.perturb_m,
        "environment": environment_info(resolve_warp_device(base["sim"]["device"], "sim.device")), "settings": [],
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    verdicts = []
    for iterations in args.iterations:
        params = read_params(args.params, [*args.overrides, f"sim.iterations={iterations}"])
        row, by_seed = measure(params, args.task, specs, args.perturb_m, args.seed)
        report["settings"].append(row)
        verdicts.append(by_seed)
        agreement_with_most_iterated(report["settings"], verdicts)
        print(f"{iterations} iterations: " + ", ".join(
            f"agreement {a['agreement']:.2f} at {a['perturb_m']:g} m ({a['mean_rms_to_first_m'] * 1e3:.1f} mm)"
            for a in row["self_agreement"]) + f"; {row['rollout_s_per_episode']:.2f} s per episode", flush=True)
        write_report_atomic(out, report, markdown(report))
        chart(report, out.with_suffix(".png"))
    print(markdown(report))


if __name__ == "__main__":
    main()
