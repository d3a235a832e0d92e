"""Stage `validate`: re-check every raw episode with the physical predicates, keep the accepted ones
with a split (data/source/trajectories.zarr) and report the counts (reports/validate.json).

An episode the simulate stage already rejected (`accepted` False) keeps its logged reason
(`first_failure`, e.g. a predicate name or a task-level reason such as "not_lifted"); the others are
checked by `first_failure` on the scene rebuilt from params `scene` and the episode's layout
(`objects`, `held`). With `validate.train_on_task_failures`, a rejected episode whose reason is its task's verdict
(not a predicate) and that passes every predicate here is written too, to the train split with `accepted` false:
physically valid data of a failed task, for the world model only. If no episode is accepted, the report is still written, then
NoAcceptedEpisodesError is raised and no output store is written, so `dvc repro` stops there.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from wc.config import ParamsError, load_section, params_hash
from wc.data.store import TrajectoryStore, copy_store
from wc.paths import VALIDATE
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig
from wc.scene.episode_scenes import EpisodeScenes
from wc.scene.scene import Scene
from wc.tasks.base import UNREACHABLE
from wc.validate.config import ValidateConfig
from wc.validate.predicates import PREDICATES, first_failure
from wc.validate.split import SPLITS, split_episodes

SECTIONS = ["validate", "scene"]
UNSPECIFIED = "unspecified"  # reason counted for a raw episode rejected without a logged first_failure
NOT_TASK_VERDICTS = {UNSPECIFIED, UNREACHABLE, *PREDICATES}  # reasons that are not a task's own verdict


class NoAcceptedEpisodesError(RuntimeError):
    """No episode passed validation: there is nothing to train on."""


def episode_state(store: TrajectoryStore, eid: str, scene: Scene) -> dict[str, np.ndarray]:
    """x, v (T, N_e, 3), action (T, 14) and link_poses (T, L, 7) of one episode, link columns in the
    scene's link_names order."""
    arrays = store.read_episode(eid, ("x", "v", "action", "link_poses"))
    links = store.episode_links(eid)
    missing = [n for n in scene.link_names if n not in links]
    if missing:
        raise ValueError(f"{store.path}: episode {eid} has no link_poses columns for {missing} "
                         f"(its links: {links}); the checks need every robot body and held object")
    arrays["link_poses"] = arrays["link_poses"][:, [links.index(n) for n in scene.link_names]]
    return arrays


def check_episode(store: TrajectoryStore, eid: str, scenes: EpisodeScenes,
                  cfg: ValidateConfig) -> tuple[str, int] | None:
    """(predicate, first failing frame) of one stored episode, or None when it passes every check."""
    scene = scenes.scene(eid)
    a = episode_state(store, eid, scene)
    return first_failure(scene, a["x"], a["v"], a["action"], a["link_poses"], cfg, frame_dt_s=store.dt)


def _rejections() -> dict[str, int]:
    return {name: 0 for name in PREDICATES}


def validate(params: dict[str, Any], raw: str | Path = VALIDATE["raw"], out: str | Path = VALIDATE["out"],
             report: str | Path = VALIDATE["report"]) -> dict[str, Any]:
    """Check every raw episode; write the accepted ones with their split to `out` (atomically) and the
    report to `report`. Returns the report."""
    cfg = load_section(params, "validate", ValidateConfig)
    scene_cfg = load_section(params, "scene", SceneConfig)
    if cfg.view_camera not in scene_cfg.cameras:
        raise ParamsError(f"{params.get('_source', '<params>')}: validate.view_camera {cfg.view_camera!r} "
                          f"is not one of scene.cameras {sorted(scene_cfg.cameras)}")
    raw, out = Path(raw), Path(out)
    if not raw.exists():
        raise FileNotFoundError(f"raw trajectory store {raw} not found: run the simulate stage first "
                                "(`dvc repro simulate` or `python -m stages.simulate`)")
    if raw.resolve() == out.resolve():
        raise ValueError(f"validate would overwrite its input {raw}: choose another output path")
    src = TrajectoryStore(raw)
    phash = params_hash(params, SECTIONS)
    scenes = EpisodeScenes(scene_cfg, src)
    started = time.perf_counter()

    tasks: dict[str, dict[str, Any]] = {}
    rejections = _rejections()
    rejected: dict[str, dict[str, Any]] = {}
    accepted: dict[str, str] = {}  # episode id -> task
    task_failures: dict[str, str] = {}  # physically valid episodes whose task failed, kept for training (id -> reason)
    with tqdm(src.episode_ids, desc="validate", unit="episode") as bar:
        for eid in bar:
            attrs = src.episode_attrs(eid)
            task = attrs["task"]
            t = tasks.setdefault(task, {"episodes": 0, "accepted": 0, "rejections": _rejections()})
            t["episodes"] += 1
            if attrs["accepted"] is False:
                reason, frame, by = attrs.get("first_failure") or UNSPECIFIED, None, "simulate"
                if cfg.train_on_task_failures and reason not in NOT_TASK_VERDICTS \
                        and check_episode(src, eid, scenes, cfg) is None:
                    task_failures[eid] = reason
                    t["task_failures_kept"] = t.get("task_failures_kept", 0) + 1
            else:
                failure = check_episode(src, eid, scenes, cfg)
                reason, frame, by = (*failure, "validate") if failure else (None, None, None)
            if reason is None:
                accepted[eid] = task
                t["accepted"] += 1
            else:
                rejections[reason] = rejections.get(reason, 0) + 1
                t["rejections"][reason] = t["rejections"].get(reason, 0) + 1
                rejected[eid] = {"task": task, "reason": reason, "frame": frame, "by": by}
            bar.set_postfix(accepted=len(accepted))

    splits = split_episodes(accepted, cfg.val_per_task, cfg.test_per_task, cfg.split_seed)
    for eid, task in accepted.items():
        tasks[task][splits[eid]] = tasks[task].get(splits[eid], 0) + 1
    for t in tasks.values():
        for s in SPLITS:
            t.setdefault(s, 0)
    result = {
        "episodes": len(src.episode_ids),
        "accepted": len(accepted),
        "rejected": len(rejected),
        "splits": {s: sum(1 for v in splits.values() if v == s) for s in SPLITS},
        "task_failures_kept": len(task_failures),  # in the train split, accepted false (train_on_task_failures)
        "rejections": rejections,
        "tasks": tasks,
        "rejected_episodes": rejected,
        "params_hash": phash,
        "source_params_hash": src.attrs["params_hash"],
        "raw": str(raw),
        "out": str(out),
    }

    def finish() -> dict[str, Any]:
        result["wall_s"] = time.perf_counter() - started
        result["environment"] = environment_info("cpu")
        write_json_atomic(report, result)
        return result

    if not accepted:
        result["out"] = None
        finish()
        raise NoAcceptedEpisodesError(
            f"validate: none of the {len(src.episode_ids)} episodes in {raw} was accepted "
            f"(rejections: { {k: v for k, v in rejections.items() if v} }); no store written to {out}. "
            f"See {report}; fix the simulation or loosen params `validate`.")
    updates = {eid: {"split": splits[eid], "accepted": True, "first_failure": None} for eid in accepted}
    updates.update({eid: {"split": "train", "accepted": False, "first_failure": reason}
                    for eid, reason in task_failures.items()})
    ids = sorted(updates, key=lambda e: (len(e), e))
    copy_store(src, out, ids, updates, created_by="stages.validate", params_hash=phash)
    return finish()


def validate_summary(result: dict[str, Any]) -> str:
    """The line `python -m stages.validate` prints."""
    failed = ", ".join(f"{k} {v}" for k, v in result["rejections"].items() if v) or "none"
    return (f"validate: {result['accepted']}/{result['episodes']} episodes accepted "
            f"(train {result['splits']['train']}, val {result['splits']['val']}, test {result['splits']['test']}); "
            f"rejected: {failed}; {result['wall_s']:.1f} s")
