"""Stage `dataset`: the LeRobot datasets of the policy comparison.

    <out>/source    accepted source episodes of params `dataset.task` in `dataset.splits`
    <out>/expanded  the same source episodes + every accepted episode of that task in the expanded store
                    (named by `dataset.expanded_arm`: a control arm from another store, e.g. newton_150)

Both read their camera views from the rendered-frames stores of the `render` stage. With
`dataset.include_expanded` true (the default) missing expanded inputs are an error, raised before
anything is written; set it false to build the source dataset only. An expanded store without a generated
episode of the task is flagged (`expanded_equals_source` in the report) or, with `dataset.require_generated`,
an error. The report (counts, timings, params hash) goes to reports/dataset.json.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from wc.config import load_section, params_hash, without_keys
from wc.data.store import TrajectoryStore
from wc.paths import DATASET
from wc.policy.card import dataset_card
from wc.policy.comparison import FLAG, WARNING, expanded_equals_source
from wc.policy.dataset import EpisodeSource, check_loads, select_episodes, write_lerobot_dataset
from wc.policy.dataset_config import DatasetConfig
from wc.reports import environment_info, write_json_atomic
from wc.render.frames import RenderedStore

SECTIONS = ["dataset"]


def _open(trajectories: Path, frames: Path, what: str) -> tuple[TrajectoryStore, RenderedStore]:
    if not trajectories.exists():
        stage = "validate" if what == "source" else "expand"
        raise FileNotFoundError(f"dataset: {what} trajectory store not found: {trajectories} (run the {stage} stage)")
    if not frames.exists():
        raise FileNotFoundError(f"dataset: {what} rendered frames not found: {frames} (run the render stage)")
    return TrajectoryStore(trajectories), RenderedStore(frames)


def build_datasets(params: dict[str, Any],
                   source_trajectories: str | Path = DATASET["source_trajectories"],
                   source_frames: str | Path = DATASET["source_frames"],
                   expanded_trajectories: str | Path = DATASET["expanded_trajectories"],
                   expanded_frames: str | Path = DATASET["expanded_frames"],
                   out: str | Path = DATASET["out"],
                   report: str | Path = DATASET["report"]) -> dict[str, Any]:
    """Write <out>/source (and <out>/expanded) and the report; returns the report."""
    cfg = load_section(params, "dataset", DatasetConfig)
    started = time.perf_counter()
    digest = params_hash(without_keys(params, "dataset", ("workers",)), SECTIONS)  # same data, any workers
    out = Path(out)
    paths = {"source trajectories": Path(source_trajectories), "source frames": Path(source_frames)}
    if cfg.include_expanded:
        paths.update({"expanded trajectories": Path(expanded_trajectories), "expanded frames": Path(expanded_frames)})
        missing = [str(p) for role, p in paths.items() if role.startswith("expanded") and not p.exists()]
        if missing:
            raise FileNotFoundError(
                f"dataset: expanded inputs not found: {', '.join(missing)}. Run the expand and render stages, "
                "or build the source dataset only with --set dataset.include_expanded=false")
    src = _open(paths["source trajectories"], paths["source frames"], "source")
    source, skipped_source = select_episodes("source", *src, cfg.task, cfg.splits)
    if not source:
        raise ValueError(f"dataset: no accepted {cfg.task!r} episodes in splits {list(cfg.splits)} of "
                         f"{paths['source trajectories']} (skipped: {skipped_source})")
    plan: dict[str, list[EpisodeSource]] = {"source": source}
    skipped: dict[str, dict[str, int]] = {"source": skipped_source}
    if cfg.include_expanded:
        exp = _open(paths["expanded trajectories"], paths["expanded frames"], "expanded")
        expanded, skipped["expanded"] = select_episodes("expanded", *exp, cfg.task)
        if not expanded and cfg.require_generated:
            raise ValueError(f"dataset: no accepted generated {cfg.task!r} episode in {paths['expanded trajectories']} "
                             f"(skipped: {skipped['expanded']}), and dataset.require_generated is true: {WARNING}. "
                             "Train a world model whose episodes pass the checks, or set it false")
        if not expanded:  # the pipeline goes on, and the reports flag the comparison as hollow
            print(f"dataset: WARNING no accepted {cfg.task!r} episodes in {paths['expanded trajectories']} "
                  f"(skipped: {skipped['expanded']}); {WARNING}", flush=True)
        plan[cfg.expanded_arm] = source + expanded

    datasets: dict[str, Any] = {"source": None, cfg.expanded_arm: None}
    for name, episodes in plan.items():
        inputs = {role: str(p) for role, p in paths.items() if name != "source" or role.startswith("source")}
        summary = write_lerobot_dataset(out / name, f"{cfg.repo_owner}/{name}", episodes, cfg,
                                        lambda s, inputs=inputs: dataset_card(s, params_hash=digest, inputs=inputs))
        check_loads(out / name, summary["repo_id"], summary["episodes"], summary["frames"])
        datasets[name] = summary
    counts = {name: summary["episodes"] for name, summary in datasets.items() if summary is not None}
    result = {FLAG: expanded_equals_source(counts), "datasets": datasets, "skipped_episodes": skipped,
              "include_expanded": cfg.include_expanded,
              "generated_episodes": len(plan[cfg.expanded_arm]) - len(source) if cfg.expanded_arm in plan else None,
              "params_hash": digest, "wall_s": time.perf_counter() - started, "environment": environment_info("cpu")}
    write_json_atomic(report, result)
    return result


def dataset_summary(result: dict[str, Any]) -> str:
    """The lines `python -m stages.dataset` prints: one per dataset written, then the wall time."""
    lines = [f"dataset {name}: {d['episodes']} episodes, {d['frames']} frames at {d['fps']} fps "
             f"-> {d['path']} ({d['wall_s']:.1f} s)" for name, d in result["datasets"].items() if d is not None]
    return "\n".join([*lines, f"dataset: {result['wall_s']:.1f} s"])
