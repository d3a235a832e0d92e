"""The markdown page and target checks of benchmarks/rollout_speed.py's report."""

from __future__ import annotations

from typing import Any

TARGETS = {"single_s_per_s": 10.0, "single_x_newton": 30.0, "batched_aggregate_s_per_s": 100.0,
           "train_s_per_step_w5": 1.0, "mse_relative_difference": 0.05}


def _fmt(value: Any, spec: str = ".2f") -> str:
    return format(value, spec) if isinstance(value, (int, float)) else "-"


def markdown(report: dict[str, Any]) -> str:
    """The report as a Markdown page: tables of the rows, ratios and the issue's targets."""
    env, ref = report["environment"], report.get("newton_for_ratios", {})
    single, multi = ref.get("single_s_per_s"), ref.get("multi_aggregate_s_per_s")
    lines = [f"# WorldContact rollout speed ({report['vertices']:,} predicted vertices)", "",
             f"Device {env['device']} ({env.get('gpu', env['cpu'])}), torch {env['torch']}, warp {env['warp']}, "
             f"newton {env['newton']}; params {report['params']} {' '.join(report['overrides'])}; episode "
             f"{report['episode']}; weights {report['weights']}; frame dt {report['dt']} s.", "",
             f"Newton for the ratios ({ref.get('source', 'none')}): single world {_fmt(single, '.3f')} s/s, "
             f"{ref.get('multi_worlds', '-')} worlds {_fmt(multi, '.3f')} s/s aggregate.", "",
             "## Single rollout (B = 1)", "",
             "| variant | ms/step | sim s / wall s | x Newton | searches / reuses | MSE vs fp32 ref m² | MSE rel. diff |",
             "|---|---|---|---|---|---|---|"]
    for r in report["single"]:
        if "ms_per_step_median" not in r:
            lines.append(f"| {r['variant']} | {r.get('error', 'skipped')} | | | | | |")
            continue
        lines.append(f"| {r['variant']} | {r['ms_per_step_median']:.2f} | {r['simulated_s_per_wall_s']:.3f} | "
                     f"{_fmt(r['simulated_s_per_wall_s'] / single if single else None, '.1f')} | "
                     f"{r['neighbour_searches']} / {r['neighbour_reuses'] or '-'} | "
                     f"{_fmt(r.get('position_mse_vs_fp32_reference_m2'), '.3g')} | "
                     f"{_fmt(r.get('position_mse_relative_difference'), '.4f')} |")
    lines += ["", "## Batched rollouts", "", "| variant | B | ms/step | aggregate sim s / wall s | x Newton multi-world |",
              "|---|---|---|---|---|"]
    for r in report["batched"]:
        if "ms_per_step_median" not in r:
            lines.append(f"| {r['variant']} | {r['batch']} | {r.get('error', 'skipped')} | | |")
            continue
        lines.append(f"| {r['variant']} | {r['batch']} | {r['ms_per_step_median']:.2f} | "
                     f"{r['simulated_s_per_wall_s_aggregate']:.3f} | "
                     f"{_fmt(r['simulated_s_per_wall_s_aggregate'] / multi if multi else None, '.1f')} |")
    lines += ["", "## Newton source simulator (this run)", "", "| worlds | bag vertices | frames | sim s / wall s per world "
              "| aggregate |", "|---|---|---|---|---|"]
    for r in report["newton"]:
        lines.append(f"| {r.get('worlds')} | {_fmt(r.get('bag_vertices'), ',')} | {r.get('timed_frames', '-')} | "
                     f"{_fmt(r.get('simulated_s_per_wall_s'), '.3f')} | "
                     f"{_fmt(r.get('simulated_s_per_wall_s_aggregate'), '.3f')} {r.get('error', '')} |")
    other = report["other"]
    lines += ["", "## Other", ""]
    if "eager_ms" in other.get("projection", {}):
        p = other["projection"]
        lines.append(f"- Topology projection P eager (the differentiable reference): {p['eager_ms']:.2f} ms; as "
                     f"rollouts call it (a CUDA graph on CUDA): {p['ms']:.2f} ms; largest difference "
                     f"{p['max_abs_difference_m']:.1e} m.")
    if "projection_ms" in other:
        lines.append(f"- Topology projection P: {other['projection_ms']:.2f} ms per step "
                     f"({other.get('projection_share_of_fastest_step', float('nan')):.0%} of the fastest step).")
    if "training" in other:
        t = other["training"]
        lines.append(f"- Optimisation step at W = {t.get('window')}: {_fmt(t.get('s_per_step_median'), '.3f')} s "
                     f"{t.get('error', '')}.")
    if "profile" in other and "ms_per_step_median" in other["profile"]:
        p = other["profile"]
        lines += ["", f"### Per-part profile, {p['variant']} ({p['ms_per_step_median']['whole step']:.2f} ms per step)",
                  "", "| part | ms | share |", "|---|---|---|"]
        whole = p["ms_per_step_median"]["whole step"]
        for name, ms in sorted(p["ms_per_step_median"].items(), key=lambda kv: -kv[1]):
            lines.append(f"| {name} | {ms:.2f} | {100 * ms / whole:.0f} % |")
    lines += ["", "## Targets", "", "| target | value | met |", "|---|---|---|"]
    for name, (value, goal, higher) in report.get("targets", {}).items():
        met = "-" if value is None else ("yes" if (value >= goal if higher else value <= goal) else "NO")
        lines.append(f"| {name} {'>=' if higher else '<='} {goal} | {_fmt(value, '.3f')} | {met} |")
    return "\n".join(lines) + "\n"


def targets_met(report: dict[str, Any]) -> dict[str, tuple[float | None, float, bool]]:
    ref = report.get("newton_for_ratios", {})
    timed = [r for r in report["single"] if "ms_per_step_median" in r]
    best = max((r["simulated_s_per_wall_s"] for r in timed), default=None)
    batched = max((r["simulated_s_per_wall_s_aggregate"] for r in report["batched"] if "ms_per_step_median" in r),
                  default=None)
    fast = [r["position_mse_relative_difference"] for r in timed if "position_mse_relative_difference" in r
            and (r["bf16"] or r["skin_m"] > 0)]
    train = report["other"].get("training", {}).get("s_per_step_median")
    return {"single rollout sim s / wall s": (best, TARGETS["single_s_per_s"], True),
            "single rollout x Newton single world": (best / ref["single_s_per_s"] if best and ref.get("single_s_per_s")
                                                     else None, TARGETS["single_x_newton"], True),
            "batched aggregate sim s / wall s": (batched, TARGETS["batched_aggregate_s_per_s"], True),
            "training s per step (W = 5)": (train, TARGETS["train_s_per_step_w5"], False),
            "position MSE relative difference (worst fast variant)": (max(fast, default=None),
                                                                      TARGETS["mse_relative_difference"], False)}
