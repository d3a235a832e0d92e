"""The headline of each kind of GPU report (`reports/gpu/*.json`), for the results page.

A report's kind is the first `ReportKind` whose file-name pattern matches. The kind declares the fields its headline
reads (dotted paths; `*` stands for every key of a mapping or every item of a list) and writes one line from those
values only. A report without one of its kind's declared fields, or one that no kind matches, is a `HeadlineError`
naming the file and the field: declare or fix its kind here (`tests/test_report_kinds.py` checks every committed
report).
"""

from __future__ import annotations

import fnmatch
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from wc.policy_eval.success import wilson_interval

BASELINES = ("robocraft", "robocook", "adaptigraph")  # evaluate's method names of the particle baselines (wc/baselines)


class HeadlineError(ValueError):
    """A GPU report lacks a field its kind declares, or no kind matches it."""


def field_value(data: Any, path: str) -> Any:
    """The value at dotted `path`; a `*` part maps every key (or list index) to the value at the rest of the path.
    KeyError(path) when a part is missing (or a `*` meets an empty or scalar value)."""
    head, _, rest = path.partition(".")
    if head == "*":
        items = data.items() if isinstance(data, Mapping) else enumerate(data) if isinstance(data, list) else ()
        found = {key: field_value(value, rest) if rest else value for key, value in items}
        if not found:
            raise KeyError(path)
        return found
    if isinstance(data, Mapping) and head in data:
        return field_value(data[head], rest) if rest else data[head]
    if isinstance(data, list) and head.isdigit() and int(head) < len(data):
        return field_value(data[int(head)], rest) if rest else data[int(head)]
    raise KeyError(path)


@dataclass(frozen=True)
class ReportKind:
    """A kind of report: the file names it covers, the fields its headline reads and the line it writes from them."""

    name: str
    patterns: tuple[str, ...]
    fields: tuple[str, ...]
    line: Callable[[dict[str, Any]], str]

    def values(self, data: Any, where: str) -> dict[str, Any]:
        """{declared field: its value in `data`}; HeadlineError naming `where` and the first missing field."""
        values = {}
        for path in self.fields:
            try:
                values[path] = field_value(data, path)
            except KeyError as err:
                raise HeadlineError(f"{where}: a {self.name!r} report without its headline field {path!r} "
                                    f"(wc/report_kinds.py declares {', '.join(self.fields)})") from err
        return values

    def headline(self, data: Any, where: str) -> str:
        return self.line(self.values(data, where))


def _g(x: Any, digits: int = 3) -> str:
    """A number in `digits` significant figures ('-' for None)."""
    return "-" if x is None else f"{x:.{digits}g}" if isinstance(x, float) else str(x)


def _policy_arms(v: dict[str, Any], key: str) -> str:
    """Successes of trials per arm (the source arm first) with the 95 % Wilson interval, and the protocol."""
    successes, trials = v[f"{key}.*.successes"], v[f"{key}.*.trials"]
    arms = []
    for name in sorted(successes, key=lambda n: n != "source"):
        low, high = wilson_interval(successes[name], trials[name])
        arms.append(f"{name} {successes[name]}/{trials[name]} ({low:.2f}-{high:.2f})")
    trials = "/".join(sorted({str(t) for t in trials.values()}))
    return (f"{', '.join(arms)} successes (95 % Wilson intervals); {v['policy_type']} on {v['task']}, {trials} "
            f"closed-loop Newton trials per policy on the same seeds, success = bag >= {v['lift_height_m']} m up for "
            f">= {v['hold_s']} s")


def _policy_comparison(v: dict[str, Any]) -> str:
    episodes = ", ".join(f"{n} {e}" for n, e in sorted(v["arms.*.episodes"].items(), key=lambda kv: kv[0] != "source"))
    return (f"{_policy_arms(v, 'arms')}; training episodes {episodes} (the generated ones by the world model with "
            f"params hash {v['data_production.worldcontact.model_params_hash']}); {v['environment.gpu']}")


def _table1(v: dict[str, Any]) -> str:
    mse, per_task = v["methods.*.position_mse_m2"], v["methods.*.per_task"]
    ours, baselines = mse["worldcontact"], [b for b in BASELINES if b in mse]
    best = min(baselines, key=mse.__getitem__)
    ratios = [min(per_task[b][t]["position_mse_m2"] for b in baselines) / s["position_mse_m2"]
              for t, s in per_task["worldcontact"].items()]
    diverged, rollouts = v["stability.methods.*.diverged"], v["stability.methods.*.rollouts"]
    return (f"WorldContact position MSE {_g(ours)} m² vs best baseline {best} {_g(mse[best])}: "
            f"{mse[best] / ours:.1f}x lower pooled over {v['held_out.rollouts']} held-out rollouts; per task "
            f"{min(ratios):.2g}-{max(ratios):.2g}x lower, lower on {sum(r > 1 for r in ratios)} of {len(ratios)} "
            f"tasks; penetration {v['methods.worldcontact.penetration_rate_pct']:.2f} %; 100-step rollouts diverged "
            f"{diverged['worldcontact']}/{rollouts['worldcontact']} (baselines "
            f"{'/'.join(str(diverged[b]) for b in baselines)} of {rollouts[best]}); {v['environment.gpu']}")


def _expand(v: dict[str, Any]) -> str:
    return (f"{v['accepted']} of {v['generated']} generated episodes accepted (acceptance {v['acceptance_rate']:.2f}), "
            f"{_g(v['accepted_per_min'])} accepted per minute; {v['source_episodes']} sources -> {v['expanded_total']} "
            f"trajectories; model {v['model.path']} (params {v['model.params_hash']}); {v['environment.gpu']}")


def _teacher(v: dict[str, Any]) -> str:
    return (f"{v['plans']} plans replayed in Newton: verdict agreement {v['agreement']:.2f}, precision "
            f"{v['precision']:.2f}, recall {v['recall']:.2f}; a generated lift is {1000 * v['mean_rms_error_m']:.1f} mm "
            f"RMS from Newton's replay of its plan; {v['environment.gpu']}")


def _simulate(v: dict[str, Any]) -> str:
    return (f"{v['accepted']} of {v['episodes']} episodes accepted, {_g(v['episodes_per_min'])} episodes per minute, "
            f"{v['bag_vertices']}-vertex bag")


def _memory(v: dict[str, Any]) -> str:
    outcomes = v["outcomes"]
    return f"failure memory of a cut run: {len(outcomes)} outcomes, {sum(1 for o in outcomes if o.get('failure'))} failed"


def _simulate_ray(v: dict[str, Any]) -> str:
    rows = [f"{e} x{w} {_g(r)}" for e, w, r in zip(v["rows.*.executor"].values(), v["rows.*.workers"].values(),
                                                  v["rows.*.episodes_per_min"].values())]
    return f"{v['task']} episodes per minute: {', '.join(rows)}"


def _simulate_workers(v: dict[str, Any]) -> str:
    rows = ", ".join(f"{w} worker(s) {_g(r)}" for w, r in zip(v["runs.*.workers"].values(),
                                                             v["runs.*.episodes_per_min"].values()))
    return f"episodes per minute with processes sharing one GPU: {rows}"


def _validate(v: dict[str, Any]) -> str:
    return f"{v['accepted']} of {v['episodes']} episodes accepted"


def _dataset(v: dict[str, Any]) -> str:
    sets = [f"{name} {d['episodes']} episodes, {d['frames']} frames" for name, d in v["datasets"].items() if d]
    return f"{'; '.join(sets)}; generated episodes {_g(v['generated_episodes'])}"


def _finetune(v: dict[str, Any]) -> str:
    sets = [f"{name} ({d['episodes']} episodes) final loss {_g(d['final_loss'])}, {d['train_s']:.0f} s"
            for name, d in v["datasets"].items()]
    return f"{v['policy_type']}, {v['steps']} steps at batch {v['batch_size']}: {'; '.join(sets)}"


def _train(prefix: str, val: str, cv: str) -> Callable[[dict[str, Any]], str]:
    def line(v: dict[str, Any]) -> str:
        return (f"best validation loss {_g(v[prefix + val])} vs constant velocity {_g(v[prefix + cv])}; held-out "
                f"rollout position MSE {_g(v[prefix + 'rollout_position_mse_m2'])} m² vs zero motion "
                f"{_g(v[prefix + 'rollout_zero_motion_mse_m2'])}")
    return line


def _train_fields(prefix: str, val: str, cv: str) -> tuple[str, ...]:
    return tuple(prefix + f for f in (val, cv, "rollout_position_mse_m2", "rollout_zero_motion_mse_m2"))


def _train_speed(v: dict[str, Any]) -> str:
    rows = ", ".join(f"{s} batch {b}: {x:.1f}x ({n:.1f} steps/s)" for s, b, x, n in
                     zip(*(v[f"rows.*.{k}"].values() for k in ("setting", "batch", "speedup", "new_steps_per_s"))))
    met = v["targets_met"]
    return f"static path vs reference: {rows}; targets met {sum(met.values())} of {len(met)}"


def _convergence(v: dict[str, Any]) -> str:
    rows = ", ".join(f"{i}: {a:.2f} accepted, {1000 * s[0]['mean_rms_to_first_m']:.1f} mm re-run distance, "
                     f"{t:.2f} s/episode" for i, a, s, t in
                     zip(*(v[f"settings.*.{k}"].values() for k in ("iterations", "accepted", "self_agreement",
                                                                  "rollout_s_per_episode"))))
    return f"Newton against itself, per VBD iteration count: {rows}"


def _fabric_stretch(v: dict[str, Any]) -> str:
    def row(r: dict[str, Any]) -> str:
        lifted = ((r.get("stretch") or {}).get("lifted") or {}).get("all") or {}
        strain = f"p99 {100 * lifted['p99']:.1f} %, worst {100 * lifted['max']:.1f} %" if lifted else "no lifted frame"
        accepted = "-" if r.get("accepted") is None else f"{r['accepted']:.2f}"
        return f"{r['setting']} ({r['iterations']} iterations): {accepted} accepted, lifted strain {strain}"
    return "bag edge strain while lifting, per setting: " + "; ".join(row(r) for r in v["settings"])


def _resolution(v: dict[str, Any]) -> str:
    rows = "; ".join(f"{n} vertices: {'stable' if ok else 'unstable'}, {_g(cost)} s per episode, agreement {_g(agree, 2)}"
                     for n, ok, cost, agree in zip(*(v[f"rows.*.{k}"].values() for k in (
                         "vertices", "stable", "newton_s_per_episode", "verdict_agreement"))))
    return f"bag resolution in Newton (needed: {v['needed_vertices']}): {rows}"


def _rollout_speed(v: dict[str, Any]) -> str:
    rows = ", ".join(f"{name} {_g(value)} (target {'>=' if higher else '<='} {_g(goal)})"
                     for name, (value, goal, higher) in v["targets"].items())
    return f"{v['vertices']} vertices: {rows}"


def _profile(v: dict[str, Any]) -> str:
    rows = ", ".join(f"{'bf16' if bf16 else 'fp32'} batch {b}, {n} vertices: {p['whole step']:.1f} ms per step"
                     for bf16, b, n, p in zip(*(v[f"runs.*.{k}"].values() for k in
                                                ("autocast_bf16", "batch", "vertices", "ms_per_step_median"))))
    return f"WorldContact step profile: {rows}"


def _paper_probe(v: dict[str, Any]) -> str:
    rows = ", ".join(f"{name}: {sum(1 for e in eps if not e.get('failure'))} of {len(eps)} pass" for name, eps in
                     zip(v["runs.*.variant"].values(), v["runs.*.episodes"].values()))
    return f"paper-scale bag, episodes passing every check per sim setting: {rows}"


def _paper_lift(v: dict[str, Any]) -> str:
    verdicts = ", ".join(str(e["verdict"][0]) for e in v["episodes"])
    return (f"{v['bag_vertices']}-vertex bag, {v['worlds']} worlds: verdicts {verdicts}; "
            f"{_g(v['simulated_s_per_wall_s_aggregate'])} simulated s per wall s")


def _expand_speed(v: dict[str, Any]) -> str:
    rows = "; ".join(f"{vert} vertices: {_g(wc)} vs Newton {_g(nw)} accepted/min = {_g(ratio)}x (acceptance {_g(acc)})"
                     for vert, nw, wc, ratio, acc in zip(*(v[f"rows.*.{k}"].values() for k in (
                         "vertices", "newton_accepted_per_min", "worldcontact_accepted_per_min", "ratio", "acceptance"))))
    return f"world-model expansion against Newton on {v['environment.gpu']}: {rows}"


def _expand_settings(v: dict[str, Any]) -> str:
    rms = v["settings.*.rms_mm"]
    rows = "; ".join(f"{name} {_g(agree, 2)} / {_g(rms[name], 3)} mm" for name, agree in v["settings.*.agreement"].items())
    return f"expansion's teacher agreement / RMS to Newton per slot-engine setting on {v['environment.gpu']}: {rows}"


def _train_scaling(v: dict[str, Any]) -> str:
    rows = "; ".join(f"{k} GPU(s): {_g(rate)} samples/s, efficiency {_g(eff, 2)}, val loss {_g(val)}"
                     for k, rate, eff, val in zip(*(v[f"rows.*.{f}"].values() for f in (
                         "gpus", "samples_per_s", "efficiency", "val_loss_after_samples"))))
    return f"world-model training on K processes (DDP), {v['environment.gpu']}: {rows}"


def _generate_scaling(v: dict[str, Any]) -> str:
    rows = "; ".join(f"{stage} on {k} GPU(s): {_g(rate)} episodes/min ({_g(speedup, 2)}x)"
                     for k, stage, rate, speedup in zip(*(v[f"rows.*.{f}"].values() for f in (
                         "gpus", "stage", "episodes_per_min", "speedup"))))
    return f"data generation across GPUs, {v['environment.gpu']}: {rows}"


def _policy_placement(v: dict[str, Any]) -> str:
    rows = "; ".join(f"{name.replace('_', ' ')} {_g(wall)} s ({_g(speedup, 2)}x)" for name, wall, speedup in zip(
        *(v[f"rows.*.{f}"].values() for f in ("schedule", "wall_s", "speedup"))))
    return f"{v['policy_type']} policy arms' training schedules, {v['environment.gpu']}: {rows}"


_POLICY = ("policy_type", "task", "lift_height_m", "hold_s")
KINDS: tuple[ReportKind, ...] = (
    ReportKind("policy comparison", ("policy_*_arms.json",),
               ("arms.*.successes", "arms.*.trials", "arms.*.episodes", *_POLICY,
                "data_production.worldcontact.model_params_hash", "environment.gpu"),
               _policy_comparison),
    ReportKind("policy training schedules", ("policy_placement_*.json",),
               ("rows.*.schedule", "rows.*.wall_s", "rows.*.speedup", "policy_type", "environment.gpu"),
               _policy_placement),
    ReportKind("policy evaluation", ("policy_*.json",),
               ("policies.*.successes", "policies.*.trials", *_POLICY),
               lambda v: _policy_arms(v, "policies")),
    ReportKind("held-out evaluation (Table 1)", ("metrics_*.json",),
               ("methods.*.position_mse_m2", "methods.*.per_task", "methods.worldcontact.penetration_rate_pct",
                "stability.methods.*.diverged", "stability.methods.*.rollouts", "held_out.rollouts", "environment.gpu"),
               _table1),
    ReportKind("expansion speed", ("expand_speed_*.json",),
               ("rows.*.vertices", "rows.*.newton_accepted_per_min", "rows.*.worldcontact_accepted_per_min",
                "rows.*.ratio", "rows.*.acceptance", "environment.gpu"), _expand_speed),
    ReportKind("expansion settings", ("expand_settings_*.json",),
               ("settings.*.agreement", "settings.*.rms_mm", "environment.gpu"), _expand_settings),
    ReportKind("expansion", ("expand_*.json",),
               ("accepted", "generated", "acceptance_rate", "accepted_per_min", "source_episodes", "expanded_total",
                "model.path", "model.params_hash", "environment.gpu"), _expand),
    ReportKind("teacher check", ("teacher_check_*.json",),
               ("plans", "agreement", "precision", "recall", "mean_rms_error_m", "environment.gpu"), _teacher),
    ReportKind("simulate on Ray", ("simulate_ray_*.json",),
               ("task", "rows.*.executor", "rows.*.workers", "rows.*.episodes_per_min"), _simulate_ray),
    ReportKind("simulate worker processes", ("simulate_workers_*.json",),
               ("runs.*.workers", "runs.*.episodes_per_min"), _simulate_workers),
    ReportKind("failure memory", ("simulate_*_memory.json",), ("outcomes",), _memory),
    ReportKind("simulate", ("simulate_*.json",), ("accepted", "episodes", "episodes_per_min", "bag_vertices"),
               _simulate),
    ReportKind("validate", ("validate_*.json",), ("accepted", "episodes"), _validate),
    ReportKind("policy dataset", ("dataset_*.json",), ("datasets", "generated_episodes"), _dataset),
    ReportKind("policy training", ("finetune_*.json",),
               ("policy_type", "steps", "batch_size", "datasets.*.episodes", "datasets.*.final_loss",
                "datasets.*.train_s", "datasets"), _finetune),
    ReportKind("training speed", ("train_speed_*.json",),
               ("rows.*.setting", "rows.*.batch", "rows.*.speedup", "rows.*.new_steps_per_s", "targets_met"),
               _train_speed),
    ReportKind("training on several GPUs", ("train_scaling_*.json",),
               ("rows.*.gpus", "rows.*.samples_per_s", "rows.*.efficiency", "rows.*.val_loss_after_samples",
                "environment.gpu"), _train_scaling),
    ReportKind("data generation on several GPUs", ("generate_scaling_*.json",),
               ("rows.*.gpus", "rows.*.stage", "rows.*.episodes_per_min", "rows.*.speedup", "environment.gpu"),
               _generate_scaling),
    ReportKind("resumable training chunks", ("train_chunks_*.json",),
               _train_fields("result.", "best_val_loss", "constant_velocity_val_loss"),
               _train("result.", "best_val_loss", "constant_velocity_val_loss")),
    ReportKind("training cut by a time limit", ("train_*_default_data.json",),
               _train_fields("best_checkpoint.", "val_loss", "constant_velocity_loss"),
               _train("best_checkpoint.", "val_loss", "constant_velocity_loss")),
    ReportKind("training", ("train_*.json",), _train_fields("", "best_val_loss", "constant_velocity_val_loss"),
               _train("", "best_val_loss", "constant_velocity_val_loss")),
    ReportKind("Newton convergence", ("newton_convergence_*.json",),
               ("settings.*.iterations", "settings.*.accepted", "settings.*.self_agreement",
                "settings.*.rollout_s_per_episode"), _convergence),
    ReportKind("fabric stretch", ("fabric_stretch_*.json",), ("settings", "settings.*.setting",
                                                              "settings.*.iterations"), _fabric_stretch),
    ReportKind("bag resolution", ("resolution_*.json",),
               ("rows.*.vertices", "rows.*.stable", "rows.*.newton_s_per_episode", "rows.*.verdict_agreement",
                "needed_vertices"), _resolution),
    ReportKind("rollout speed", ("rollout_speed_*.json",), ("vertices", "targets"), _rollout_speed),
    ReportKind("rollout profile", ("rollout_profile_*.json",),
               ("runs.*.autocast_bf16", "runs.*.batch", "runs.*.vertices", "runs.*.ms_per_step_median"), _profile),
    ReportKind("paper-scale physics probe", ("paper_scale_physics_probe_*.json",),
               ("runs.*.variant", "runs.*.episodes"), _paper_probe),
    ReportKind("paper-scale lift", ("lift_handle_paper_scale_*.json",),
               ("bag_vertices", "worlds", "episodes", "simulated_s_per_wall_s_aggregate"), _paper_lift),
)


def kind_of(name: str) -> ReportKind:
    """The kind of the report file `name`; HeadlineError when no kind's pattern matches it."""
    for kind in KINDS:
        if any(fnmatch.fnmatchcase(name, pattern) for pattern in kind.patterns):
            return kind
    raise HeadlineError(f"{name}: no report kind matches this file name: declare its kind and headline fields "
                        "in wc/report_kinds.py")


def kind_named(name: str) -> ReportKind:
    """The report kind called `name` (e.g. "policy evaluation"); KeyError naming the kinds when there is none."""
    for kind in KINDS:
        if kind.name == name:
            return kind
    raise KeyError(f"no report kind {name!r}; kinds: {[k.name for k in KINDS]}")


def report_headline(path: Path) -> tuple[str, str]:
    """(kind name, headline line) of the GPU report at `path`; HeadlineError (a ValueError) when it is not JSON,
    no kind matches it or it lacks a declared field."""
    kind = kind_of(path.name)
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise HeadlineError(f"{path} is not valid JSON ({err})") from err
    return kind.name, kind.headline(data, str(path))
