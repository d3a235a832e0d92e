"""The Table-1 report of a GPU run: the evaluate stage's metrics beside the paper's figures, the training budget of
every learned method, single and batched speed, and a speed-accuracy chart with both.

    python -m wc.eval.table_report --metrics reports/gpu/metrics_h100_table1.json \
        --trainings reports/gpu/table1 --speed reports/gpu/table1/rollout_speed_table1.json \
        --out reports/gpu/metrics_h100_table1.md --chart reports/gpu/speed_accuracy_h100_table1_batched.png

Inputs: `metrics` (wc.eval.stage.evaluate's report), the training reports in `trainings` (train_<method>.json of the
train stage, train_baseline_<method>.json of train_baselines), and a benchmarks.rollout_speed report (`speed`) made
on the same device: its batched WorldContact rows and its multi-world Newton rows become the batched points of the
chart, each at the accuracy its method has on the chart's rollouts (batching does not change a rollout).
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path
from typing import Any

from wc.atomic import write_atomic
from wc.baselines import BASELINES
from wc.eval.plots import plot_speed_accuracy, speed_accuracy_rows

# The paper's Table 1 (its own data; ../shared/reference/baselines.md): position MSE, velocity MSE, penetration %
PAPER_TABLE1 = {"robocraft": (0.0598, 0.0106, 13.88), "robocook": (0.0575, 0.0105, 10.28),
                "adaptigraph": (0.0323, 0.0098, 24.84), "worldcontact": (0.0002, 0.0002, 0.35)}
MARGIN_GOAL = 10.0  # the paper's margin: WorldContact's position MSE this many times below the best baseline's
PENETRATION_GOAL_PCT = 0.35


def _fmt(value: float | None, spec: str = ".2e") -> str:
    return "-" if value is None else format(value, spec)


def training_rows(trainings: Path) -> dict[str, dict[str, Any]]:
    """Per learned method: steps, wall time, s/step, what stopped it and its validation loss (from the reports)."""
    rows = {}
    for path in sorted(trainings.glob("train_*.json")):
        report = json.loads(path.read_text())
        if "baselines" in report:
            for name, b in report["baselines"].items():
                rows[name] = {"steps": b["steps_done"], "wall_s": b["wall_s"], "s_per_step": b["s_per_step_median"],
                              "stopped_by": b["stopped_by"], "val_loss": b["best_val_loss"]}
        elif isinstance(report.get("steps"), dict):  # the train stage's: {"base": n, "projection": m}
            rows[path.stem.removeprefix("train_")] = {
                "steps": sum(report["steps"].values()), "wall_s": report.get("wall_s"),
                "s_per_step": report.get("s_per_step_median"), "stopped_by": "steps",
                "val_loss": report.get("best_val_loss")}
    return rows


def batched_rows(speed: dict[str, Any], chart: dict[str, dict[str, Any]], kinds: dict[str, str]) -> list[list[object]]:
    """Chart rows of the speed report's batched WorldContact (bf16) and multi-world Newton measurements, at the chart
    accuracy of the matching single method (worldcontact_bf16 / newton_reference where evaluated)."""
    rows: list[list[object]] = []
    wc = next((m for m in ("worldcontact_bf16", "worldcontact") if m in chart), None)
    for r in speed.get("batched", []):
        if wc and r.get("bf16") and "skin" not in str(r.get("variant")) and r.get("simulated_s_per_wall_s_aggregate"):
            rows.append([f"{wc} B={r['batch']}", kinds.get(wc, "worldcontact"), r["simulated_s_per_wall_s_aggregate"],
                         chart[wc]["position_mse_m2"], chart[wc]["penetration_rate_pct"]])
    if "newton_reference" in chart:
        for r in speed.get("newton", []):
            if r.get("worlds", 1) > 1 and r.get("simulated_s_per_wall_s_aggregate"):
                rows.append([f"newton_reference {r['worlds']} worlds", "newton", r["simulated_s_per_wall_s_aggregate"],
                             chart["newton_reference"]["position_mse_m2"],
                             chart["newton_reference"]["penetration_rate_pct"]])
    return rows


def method_kinds(metrics: dict[str, Any]) -> dict[str, str]:
    """Kind of every charted method: as the report records it, else from the Newton settings and the names."""
    if "kinds" in metrics:
        return dict(metrics["kinds"])
    newton = metrics["speed_accuracy"].get("newton", {})
    named = {"zero_motion": "zero_motion", "constant_velocity": "constant_velocity"}
    return {m: "newton" if m in newton else "baseline" if m in BASELINES else named.get(m, "worldcontact")
            for m in metrics["speed_accuracy"]["methods"]}


def chart_rows(metrics: dict[str, Any], speed: dict[str, Any] | None) -> tuple[list[list[object]], list[list[object]]]:
    """The chart's rows: one rollout per method (the metrics report's) and the batched ones (the speed report's)."""
    chart, kinds = metrics["speed_accuracy"]["methods"], method_kinds(metrics)
    single = speed_accuracy_rows(chart, frame_dt(metrics, speed), kinds)
    return single, batched_rows(speed, chart, kinds) if speed else []


def frame_dt(metrics: dict[str, Any], speed: dict[str, Any] | None) -> float:
    """The frame dt of the evaluated store (the metrics report's, else the speed report's)."""
    dt = metrics.get("dt") or (speed or {}).get("dt")
    if not dt:
        raise ValueError("table_report: neither the metrics nor the speed report gives the frame dt")
    return float(dt)


def _best_baseline(methods: dict[str, dict[str, Any]]) -> str | None:
    scored = [b for b in BASELINES if b in methods and methods[b]["position_mse_m2"] is not None]
    return min(scored, key=lambda b: methods[b]["position_mse_m2"]) if scored else None


def whole_episode_markdown(metrics: dict[str, Any]) -> list[str]:
    """Lines of the whole-episode section: the per-task ratio summary, its per-task rows and the per-phase MSEs
    (none for a report made before evaluate had them)."""
    summary, methods = metrics.get("whole_episode"), metrics["methods"]
    if not summary:
        return []
    pen = summary["penetration_pct"]
    mean = summary["mean_task_ratio"]
    lines = ["", f"## Whole held-out episodes ({summary['rollouts']} rollouts of up to "
                 f"{metrics['held_out']['episode_frames']} steps from each span's first frame)", "",
             f"- {summary['subject']}: the best of {', '.join(summary['baselines'])} has {_fmt(mean, '.1f')}x its "
             f"position MSE as the mean over tasks of per-task ratios (goal >= {MARGIN_GOAL:g}x: "
             f"{'met' if mean is not None and mean >= MARGIN_GOAL else 'not met'}), {_fmt(summary['worst_task_ratio'], '.2f')}x "
             f"on the worst task, {_fmt(summary['pooled_ratio'], '.1f')}x pooled over tasks",
             f"- penetration {_fmt(pen, '.2f')} % (goal <= {PENETRATION_GOAL_PCT} %: "
             f"{'met' if pen is not None and pen <= PENETRATION_GOAL_PCT else 'not met'})", "",
             f"| task | best baseline | its position MSE m² | {summary['subject']} m² | ratio |", "|---|---|---|---|---|"]
    lines += [f"| {task} | {row['best_baseline'] or '-'} | {_fmt(row['best_baseline_mse_m2'])} | "
              f"{_fmt(row['subject_mse_m2'])} | {_fmt(row['ratio'], '.2f')} |" for task, row in summary["per_task"].items()]
    phases = list(dict.fromkeys(p for m in methods.values() for p in m.get("per_phase", {})))
    if phases:
        lines += ["", f"## Position MSE per motion phase (m², {metrics['held_out']['rollout_frames']}-step rollouts from "
                      "each phase's first frame)", "", "| method | " + " | ".join(phases) + " |",
                  "|---|" + "---|" * len(phases)]
        lines += [f"| {name} | " + " | ".join(_fmt(m["per_phase"].get(p, {}).get("position_mse_m2")) for p in phases)
                  + " |" for name, m in methods.items()]
    return lines


def map_back_markdown(metrics: dict[str, Any]) -> list[str]:
    """Lines of the map-back section: each particle baseline's floor (its error with every particle right) beside its
    held-out position MSE (none for a report made before evaluate measured it)."""
    floors = metrics.get("map_back")
    if not floors:
        return []
    lines = ["", "## Map-back floor (the recorded held-out frames rebuilt from each baseline's own particles)", "",
             "| baseline | particles / vertices | floor position MSE m² | its held-out position MSE m² | floor share |",
             "|---|---|---|---|---|"]
    for name, floor in floors.items():
        mse = metrics["methods"].get(name, {}).get("position_mse_m2")
        share = floor["position_mse_m2"] / mse if mse and floor["position_mse_m2"] is not None else None
        sizes = ", ".join(f"{size['particles']} / {size['vertices']}" for size in floor["layouts"])
        lines.append(f"| {name} | {sizes} | {_fmt(floor['position_mse_m2'])} | {_fmt(mse)} | "
                     f"{_fmt(share * 100 if share is not None else None, '.1f')} % |")
    return lines


def table_markdown(metrics: dict[str, Any], trainings: dict[str, dict[str, Any]], title: str,
                   rows: tuple[list[list[object]], list[list[object]]]) -> str:
    """The report: Table 1 with the paper's figures, per-task position MSE, training budgets, speed (`rows`, from
    chart_rows), stability."""
    methods, stability = metrics["methods"], metrics["stability"]["methods"]
    best = _best_baseline(methods)
    best_mse = methods[best]["position_mse_m2"] if best else None
    env = metrics["environment"]
    lines = [f"# {title}", "",
             f"{env.get('gpu', env.get('device'))}; torch {env.get('torch')}, warp {env.get('warp')}, newton "
             f"{env.get('newton')}. Held-out data: {metrics['held_out']['rollouts']} rollouts of "
             f"{metrics['held_out']['rollout_frames']} steps ({metrics['held_out']['source']}); long rollouts: "
             f"{metrics['stability']['stability_frames']} steps ({metrics['stability']['source']}).", "",
             "## Table 1 (held-out rollouts)", "",
             "| method | position MSE m² | velocity MSE m²/s² | penetration % | contact-area penetration % | "
             f"x below {best or 'best baseline'} | long rollouts diverged | paper: position / velocity MSE, penetration % |",
             "|---|---|---|---|---|---|---|---|"]
    for name, m in methods.items():
        ratio = best_mse / m["position_mse_m2"] if best_mse and m["position_mse_m2"] else None
        div = stability.get(name, {})
        paper = PAPER_TABLE1.get(name)
        lines.append(f"| {name} | {_fmt(m['position_mse_m2'])} | {_fmt(m['velocity_mse_m2_s2'])} | "
                     f"{_fmt(m.get('penetration_rate_pct'), '.2f')} | {_fmt(m.get('contact_penetration_rate_pct'), '.2f')} | "
                     f"{_fmt(ratio, '.1f')} | {div.get('diverged', '-')}/{div.get('rollouts', '-')} | "
                     f"{' / '.join(map(str, paper[:2])) + f', {paper[2]}' if paper else '-'} |")
    gt = metrics.get("ground_truth", {})
    lines += [f"| (recorded data) | 0 | 0 | {_fmt(gt.get('penetration_rate_pct'), '.2f')} | "
              f"{_fmt(gt.get('contact_penetration_rate_pct'), '.2f')} | - | - | - |", ""]
    tasks = sorted({t for m in methods.values() for t in m["per_task"]})
    lines += ["## Position MSE per task (m²)", "", "| method | " + " | ".join(tasks) + " |",
              "|---|" + "---|" * len(tasks)]
    lines += [f"| {name} | " + " | ".join(_fmt(m["per_task"].get(t, {}).get("position_mse_m2")) for t in tasks) + " |"
              for name, m in methods.items()]
    lines += whole_episode_markdown(metrics)
    lines += map_back_markdown(metrics)
    if trainings:
        lines += ["", "## Training budget (each learned method on the same train split)", "",
                  "| method | steps | wall min | s/step (median) | stopped by | best validation loss |", "|---|---|---|---|---|---|"]
        lines += [f"| {n} | {t['steps']} | {_fmt(t['wall_s'] / 60 if t['wall_s'] else None, '.1f')} | "
                  f"{_fmt(t['s_per_step'], '.3f')} | {t['stopped_by']} | {_fmt(t['val_loss'], '.4g')} |"
                  for n, t in trainings.items()]
    lines += ["", f"## Speed and accuracy ({metrics['speed_accuracy']['rollouts']} charted rollouts, every method)", "",
              "| method | sim s / wall s (one rollout) | position MSE m² | penetration % |", "|---|---|---|---|"]
    single, batched = rows
    for name, _, s, mse, pen in single:
        lines.append(f"| {name} | {_fmt(s, '.3g')} | {_fmt(mse)} | {_fmt(pen, '.2f')} |")
    for name, _, s, mse, pen in batched:
        lines.append(f"| {name} (batched, aggregate) | {_fmt(s, '.3g')} | {_fmt(mse)} | {_fmt(pen, '.2f')} |")
    lines += ["", "## Stability (first step at which a long rollout diverges)", "",
              "| method | diverged | median first divergence step of those that did |", "|---|---|---|"]
    for name, s in stability.items():
        steps = [v for k, v in s["first_divergence_step"].items() if "/" in k and v is not None]
        lines.append(f"| {name} | {s['diverged']}/{s['rollouts']} | {_fmt(statistics.median(steps) if steps else None, '.0f')} |")
    if best_mse and "worldcontact" in methods:
        wc = methods["worldcontact"]
        margin = best_mse / wc["position_mse_m2"]
        pen = wc.get("penetration_rate_pct")
        lines += ["", "## Against the paper's margin", "",
                  f"- position MSE {margin:.1f}x below the best baseline ({best}); goal >= {MARGIN_GOAL:g}x: "
                  f"{'met' if margin >= MARGIN_GOAL else 'not met'}",
                  f"- penetration {_fmt(pen, '.2f')} %; goal <= {PENETRATION_GOAL_PCT} %: "
                  f"{'met' if pen is not None and pen <= PENETRATION_GOAL_PCT else 'not met'}"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--metrics", required=True)
    parser.add_argument("--trainings", default=None, help="folder of train_<method>.json reports")
    parser.add_argument("--speed", default=None, help="benchmarks.rollout_speed report of the same device")
    parser.add_argument("--out", required=True, help="markdown report")
    parser.add_argument("--chart", default=None, help="speed-accuracy PNG with the batched points")
    parser.add_argument("--title", default="Table 1 on the GPU")
    args = parser.parse_args(argv)
    metrics = json.loads(Path(args.metrics).read_text())
    speed = json.loads(Path(args.speed).read_text()) if args.speed else None
    trainings = training_rows(Path(args.trainings)) if args.trainings else {}
    rows = chart_rows(metrics, speed)
    text = table_markdown(metrics, trainings, args.title, rows)
    write_atomic(args.out, lambda tmp: tmp.write_text(text))
    if args.chart:
        plot_speed_accuracy(rows[0] + rows[1], args.chart, metrics["speed_accuracy"]["rollouts"])


if __name__ == "__main__":
    main()
