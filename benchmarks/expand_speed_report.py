"""The expansion-speed benchmark's table and chart (benchmarks/expand_speed.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from wc.expand.teacher import expansion_weighted
from wc.reports import cell, pyplot, save_figure_atomic, write_report_atomic


def markdown(report: dict[str, Any]) -> str:
    """The report as a short page: the headline rows, Newton per worlds count, the expansion and its timing."""
    env = report["environment"]
    lines = [f"# Accepted {report['task']} episodes per minute: Newton against the world model's expansion", "",
             f"{env.get('gpu', env.get('device'))}; torch {env.get('torch')}, warp {env.get('warp')}, newton "
             f"{env.get('newton')}. {report['what']}.", "",
             "| run | vertices | Newton accepted/min (worlds) | WorldContact accepted/min | ratio | acceptance | "
             "teacher agreement: sampled plans (plans) / expansion-weighted | RMS to Newton mm: sampled / accepted "
             "plans |", "|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        lines.append(f"| {r.get('run', '-')} | {r['vertices']} | {cell(r['newton_accepted_per_min'])} "
                     f"({r['newton_worlds']}) | {cell(r['worldcontact_accepted_per_min'])} | {cell(r['ratio'], '.2f')} "
                     f"| {cell(r['acceptance'], '.2f')} | {cell(r['teacher_agreement'], '.2f')} ({r['teacher_plans']}) "
                     f"/ {cell(r.get('teacher_agreement_expansion'), '.2f')} | {cell(r['teacher_rms_mm'])} / "
                     f"{cell(r.get('teacher_rms_mm_accepted'))} |")
    lines += ["", "## Newton per worlds count (reset, settle, plan, simulate, checks; after a warm-up batch)", "",
              "| run | worlds | episodes | accepted | s | accepted/min | episodes/min | acceptance |",
              "|---|---|---|---|---|---|---|---|"]
    for r in report["newton"]:
        lines.append(f"| {r.get('run', '-')} | {r['worlds']} | {r['episodes']} | {r['accepted']} | {r['seconds']:.1f} | "
                     f"{r['accepted_per_min']:.1f} | {r['episodes_per_min']:.1f} | {r['acceptance']:.2f} |")
    for r in report["rows"]:
        if r.get("timing"):
            lines += ["", f"## Where the expansion's time went ({r.get('run', '')}, {r.get('slots')} slots, "
                          f"{r.get('generated')} generated)", "", "| phase | s |", "|---|---|"]
            lines += [f"| {k} | {v:.1f} |" for k, v in r["timing"].items()]
    e = report.get("expand")
    if e:
        lines += ["", f"## The expansion ({e['engine']} engine, {e.get('slots')} slots)", "",
                  f"{e['accepted']} of {e['generated']} generated accepted in {e['wall_s']:.1f} s "
                  f"({e['accepted_per_min']:.1f} per minute); rejections: "
                  f"{', '.join(f'{k} {v}' for k, v in e['rejections'].items() if v) or 'none'}; restarts "
                  f"{e.get('restarts')}.", "", "| phase | s |", "|---|---|"]
        lines += [f"| {k} | {v:.2f} |" for k, v in (e.get("timing") or {}).items()]
    t = report.get("teacher")
    if t:
        lines += ["", f"Teacher check: {t['plans']} plans, agreement {cell(t['agreement'], '.2f')}, precision "
                      f"{cell(t['precision'], '.2f')}, recall {cell(t['recall'], '.2f')}, Newton accepts "
                      f"{cell(t['newton_accepts'], '.2f')} (one verdict for all: "
                      f"{cell(t['constant_agreement'], '.2f')}), mean RMS {cell(t['mean_rms_error_m'], scale=1e3)} mm."]
    return "\n".join(lines) + "\n"


def chart(report: dict[str, Any], path: Path) -> None:
    """Accepted episodes per minute of Newton (each worlds count) and of the expansion, with the ratio."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    labels = [f"Newton {r['worlds']} worlds {r.get('run', '')}".strip() for r in report["newton"]]
    values = [r["accepted_per_min"] for r in report["newton"]]
    colors = ["tab:gray"] * len(values)
    for r in report["rows"]:
        labels.append(f"WorldContact {r.get('run', '')} ({r['vertices']} v)")
        values.append(r["worldcontact_accepted_per_min"])
        colors.append("tab:blue")
    ax.barh(labels, values, color=colors)
    for y, v in enumerate(values):
        ax.text(v, y, f" {v:.0f}", va="center")
    ratios = ", ".join(f"{r['ratio']:.2f}x" for r in report["rows"] if r["ratio"])
    ax.set_xlabel("accepted episodes per minute (checks included)")
    ax.set_title(f"{report['task']}: world model vs Newton ({ratios})", fontsize=10)
    fig.tight_layout()
    save_figure_atomic(fig, path)
    plt.close(fig)


def _mm(metres: float | None) -> float | None:
    return None if metres is None else 1e3 * metres


def speed_row(newton: list[dict[str, Any]], expanded: dict[str, Any], teacher: dict[str, Any] | None
              ) -> dict[str, Any]:
    """One run's headline row: Newton's best worlds count of that run against its expansion, and the teacher check
    (the sampled plans' figures, and the expansion-weighted agreement: wc.expand.teacher.expansion_weighted) where
    it ran."""
    best = max(newton, key=lambda r: r["accepted_per_min"])
    teacher = teacher or {}
    weighted = expansion_weighted(teacher["confusion"], expanded["accepted"],
                                  expanded["generated"] - expanded["accepted"]) if teacher.get("confusion") else {}
    return {"vertices": expanded.get("vertices", 306), "newton_worlds": best["worlds"],
            "newton_accepted_per_min": best["accepted_per_min"],
            "worldcontact_accepted_per_min": expanded["accepted_per_min"],
            "ratio": expanded["accepted_per_min"] / best["accepted_per_min"] if best["accepted_per_min"] else None,
            "acceptance": expanded["acceptance_rate"], "generated": expanded["generated"],
            "teacher_agreement": teacher.get("agreement"), "teacher_plans": teacher.get("plans"),
            "teacher_agreement_expansion": weighted.get("agreement"),
            "teacher_rms_mm": _mm(teacher.get("mean_rms_error_m")),
            "teacher_rms_mm_accepted": _mm(teacher.get("accepted_mean_rms_error_m")),
            "timing": expanded.get("timing"), "slots": expanded.get("slots"),
            "projection_stats": expanded.get("projection_stats")}


def combined(runs: list[tuple[str, dict[str, Any], dict[str, Any]]]) -> dict[str, Any]:
    """One report from several benchmark runs on one device: (label, benchmark JSON, its expand report) each; a row
    per run (`speed_row`; teacher figures None where the run stopped before its check)."""
    rows, newton = [], []
    for label, bench, expanded in runs:
        newton += [{**r, "run": label} for r in bench["newton"]]
        rows.append({"run": label, **speed_row(bench["newton"], expanded, bench.get("teacher"))})
    first = runs[0][1]
    return {"benchmark": "expand_speed", "task": first["task"], "environment": first["environment"],
            "what": first["what"], "commands": [r[1]["command"] for r in runs], "rows": rows, "newton": newton}


def main(argv: list[str] | None = None) -> None:
    """python -m benchmarks.expand_speed_report --run LABEL BENCH.json EXPAND.json [...] --out FILE.json: the combined
    report, its .md and .png."""
    import argparse  # noqa: PLC0415
    import json  # noqa: PLC0415

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--run", nargs=3, action="append", metavar=("LABEL", "BENCH", "EXPAND"), required=True)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    report = combined([(label, json.loads(Path(b).read_text()), json.loads(Path(e).read_text()))
                       for label, b, e in args.run])
    out = Path(args.out)
    write_report_atomic(out, report, markdown(report))
    chart(report, out.with_suffix(".png"))


if __name__ == "__main__":
    main()
