"""The expansion's accuracy per slot-engine setting against the reference engine, beside the frame cost of the bounded
step's pair capacity (scripts/gpu/expand_settings_accuracy.sh's reports, benchmarks.expand_smoke per capacity).

    python -m benchmarks.expand_settings_report --runs reports/gpu/expand_settings_accuracy \
        --out reports/gpu/expand_settings_accuracy.md --png reports/gpu/expand_settings_accuracy.png \
        --json reports/gpu/expand_settings_accuracy.json

Reads expand_<setting>.json and teacher_check_<setting>.json (one row per setting), smoke_pairs<N>.json (ms per frame
of 256 slots at pair capacity N); writes a table, a chart of teacher agreement and RMS against frame cost, and the
rows as JSON (the results page's headline, wc/report_kinds.py).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from wc.reports import pyplot, save_figure_atomic

SETTINGS = {  # setting: what differs from the slot engine as shipped before this study
    "slots": "slot engine: bf16 network, 10 + 20 projection passes, 96 pairs per episode",
    "fp32": "fp32 network",
    "passes50": "50 + 50 projection passes",
    "pairs512": "512 bounded-step pairs, 256 self-contact pairs per episode",
    "all_undone": "fp32, 50 + 50 passes, 512 / 256 pairs",
    "reference": "reference engine (expand.engine=batches): fp32, passes to 0.1 mm, every near pair",
}


def rows(folder: Path) -> list[dict[str, Any]]:
    """One row per setting whose expand and teacher-check reports are in folder."""
    out = []
    for name, what in SETTINGS.items():
        exp, chk = folder / f"expand_{name}.json", folder / f"teacher_check_{name}.json"
        if not (exp.exists() and chk.exists()):
            continue
        e, c = json.loads(exp.read_text()), json.loads(chk.read_text())
        stats = e.get("projection_stats") or {}
        out.append({"setting": name, "what": what, "generated": e["generated"], "accepted": e["accepted"],
                    "not_lifted": e["rejections"].get("not_lifted", 0), "pairs_dropped": stats.get("pairs_dropped"),
                    "plans": c["plans"], "agreement": c["agreement"], "constant_agreement": c["constant_agreement"],
                    "precision": c["precision"], "recall": c["recall"], "rms_mm": 1000 * c["mean_rms_error_m"],
                    "gpu": e["environment"].get("gpu")})
    return out


def frame_costs(folder: Path) -> list[dict[str, Any]]:
    """(pair capacity, ms per frame, slots) from the smoke runs, by capacity."""
    costs = []
    for path in folder.glob("smoke_pairs*.json"):
        row = json.loads(path.read_text())["rows"][0]
        costs.append({"pair_capacity": int(path.stem.removeprefix("smoke_pairs")), "ms_per_frame": row["ms_per_frame"],
                      "slots": row["slots"], "untangle_s": row["parts_s"]["untangle"]})
    return sorted(costs, key=lambda r: r["pair_capacity"])


def markdown(settings: list[dict[str, Any]], costs: list[dict[str, Any]]) -> str:
    lines = ["# The expansion's agreement with Newton per slot-engine setting", "",
             f"{settings[0]['gpu']}; every setting expands the same fresh Newton lift_handle data "
             "with the same model and seed, side by side on one GPU; the teacher check replays every plan in Newton "
             "at the same VBD iterations (20).", "",
             "| setting | what | accepted / generated | not_lifted | pairs dropped | teacher agreement (one verdict "
             "for all) | precision | recall | RMS to Newton mm |", "|---|---|---|---|---|---|---|---|---|"]
    for r in settings:
        dropped = "-" if r["pairs_dropped"] is None else f"{r['pairs_dropped']:,.0f}"
        lines.append(f"| {r['setting']} | {r['what']} | {r['accepted']} / {r['generated']} | {r['not_lifted']} | "
                     f"{dropped} | {r['agreement']:.2f} ({r['constant_agreement']:.2f}) | {r['precision']:.2f} | "
                     f"{r['recall']:.2f} | {r['rms_mm']:.1f} |")
    lines += ["", "Frame cost of the slot engine against the bounded step's pair capacity (`benchmarks.expand_smoke`, "
              "graphs on, 30 frames after a warm-up):", "", "| pair capacity | slots | ms per frame | untangle s |",
              "|---|---|---|---|"]
    lines += [f"| {c['pair_capacity']} | {c['slots']} | {c['ms_per_frame']:.0f} | {c['untangle_s']:.2f} |" for c in costs]
    return "\n".join(lines) + "\n"


def chart(settings: list[dict[str, Any]], costs: list[dict[str, Any]], png: Path) -> None:
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for r in settings:
        a.scatter(r["rms_mm"], r["agreement"])
        a.annotate(r["setting"], (r["rms_mm"], r["agreement"]), fontsize=8)
    a.set_xlabel("mean RMS to Newton's replay [mm]")
    a.set_ylabel("teacher agreement")
    a.set_title("accuracy per setting")
    b.plot([c["pair_capacity"] for c in costs], [c["ms_per_frame"] for c in costs], marker="o")
    b.set_xlabel("bounded-step pair capacity per episode")
    b.set_ylabel("ms per frame")
    b.set_title(f"frame cost ({costs[0]['slots'] if costs else '?'} slots)")
    save_figure_atomic(fig, png)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--png", type=Path, required=True)
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args()
    settings, costs = rows(args.runs), frame_costs(args.runs)
    if not settings:
        raise SystemExit(f"expand_settings_report: error: no expand_*/teacher_check_* pairs in {args.runs}")
    args.out.write_text(markdown(settings, costs))
    args.json.write_text(json.dumps({"environment": {"gpu": settings[0]["gpu"]}, "settings": {r["setting"]: r for r in settings},
                                     "frame_cost": costs}, indent=2) + "\n")
    chart(settings, costs, args.png)
    print(args.out.read_text())


if __name__ == "__main__":
    main()
