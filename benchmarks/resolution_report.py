"""The resolution study's table and chart (benchmarks/resolution.py): Newton's cost per episode against its fidelity
to the finest stable bag."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from wc.reports import cell, pyplot, save_figure_atomic


def markdown(report: dict[str, Any]) -> str:
    """One row per resolution, then the needed resolution and how it was chosen."""
    env = report["environment"]
    lines = [f"# Bag resolution: {report['task']}, {report['plans']} plans at every resolution", "",
             f"Device {env['device']} ({env.get('gpu', env.get('cpu'))}), warp {env.get('warp')}, newton "
             f"{env.get('newton')}; params {report['params']} {' '.join(report['overrides'])}; agent seed "
             f"{report['seed']}. Distances: RMS over {report['points']} common surface points (sampled on the finest "
             f"rest surface), per plan over its frames, then the mean; noise floor: Newton replayed again (reverse "
             f"batch order, frame-0 noise {report['noise_m']:g} m). Image difference: mean absolute pixel difference "
             "against the reference, 0-1.", "",
             "| vertices | own overrides | verdicts | stable | Newton s per episode | verdict agreement | RMS mm | "
             "noise floor mm | lifted p99 / max stretch % | image diff top / wrist |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        verdicts = ", ".join(f"{k} {n}" for k, n in r["verdicts"].items()) or "-"
        image = r.get("image_diff") or {}
        mark = " (reference)" if r.get("reference") else ""
        lines.append(f"| {r['vertices']}{mark} | {', '.join(r['overrides']) or '-'} | {verdicts} | "
                     f"{'yes' if r['stable'] else 'no'} | {r['newton_s_per_episode']:.2f} | "
                     f"{cell(r.get('verdict_agreement'), '.2f')} | {cell(r.get('rms_mm'))} | "
                     f"{cell(r['noise_floor_mm'])} | "
                     f"{cell(r['p99_stretch'], scale=100)} / {cell(r['max_stretch'], scale=100)} | "
                     f"{cell(image.get('top'), '.3f')} / {cell(image.get('wrist'), '.3f')} |")
    needed = report.get("needed_vertices")
    rule = (f"the coarsest stable resolution whose verdicts agree >= {report['agreement_needed']:g} with the reference "
            "and whose distance is within the reference's noise floor")
    if "finished" not in report:
        lines += ["", "Not finished: the comparison is made once every resolution has run."]
    elif needed is not None and any(r.get("reference") and r["vertices"] == needed for r in report["rows"]):
        lines += ["", f"Needed: **at least {needed}** vertices ({rule}): no coarser resolution matches the reference, "
                      "the finest that ran stably, and nothing finer confirms the reference itself."]
    else:
        lines += ["", f"Needed: **{needed if needed is not None else 'none found'}** vertices: {rule}."]
    return "\n".join(lines) + "\n"


def chart(report: dict[str, Any], path: Path) -> None:
    """Newton's cost per episode against the distance to the reference, a point per resolution, the reference's noise
    floor as a line."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    rows = [r for r in report["rows"] if r.get("rms_mm") is not None and r["rms_mm"] < float("inf")]
    for r in rows:
        ax.scatter(r["newton_s_per_episode"], max(r["rms_mm"], 1e-3), color="tab:blue" if r["stable"] else "tab:red")
        ax.annotate(f" {r['vertices']} v{'' if r['stable'] else ' (unstable)'}",
                    (r["newton_s_per_episode"], max(r["rms_mm"], 1e-3)), fontsize=8)
    floor = next((r["noise_floor_mm"] for r in report["rows"] if r.get("reference")), None)
    if floor:
        ax.axhline(floor, color="gray", ls="--", lw=1, label=f"reference noise floor {floor:.1f} mm")
        ax.legend(fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("Newton rollout s per episode")
    ax.set_ylabel("RMS distance to the reference [mm]")
    ax.set_title(f"Bag resolution: cost against fidelity ({report['task']}, {report['environment']['device']})",
                 fontsize=10)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    save_figure_atomic(fig, path)
    plt.close(fig)
