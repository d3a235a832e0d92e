"""The render stage: trajectory stores -> rendered-frames stores (top and wrist RGB views per frame),
a JSON report and a contact sheet PNG.

Every selected episode is rendered at the trajectory's frame rate (one image per stored frame, fps =
1 / dt) by Newton's SensorCamera (wc.render.renderer). Outputs are written atomically; a missing input
store, a camera link an episode lacks, or a task filter that matches nothing fails with a clear error.
`render.episodes_per_unit` episodes are a work unit (wc.render.worker), rendered in this process, as Ray tasks
(`executor: ray`) or in a process per GPU (`executor: processes`); the frames are written in episode order any way.
"""

from __future__ import annotations

import secrets
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from wc.config import ParamsError, load_section, params_hash, without_keys
from wc.data.store import TrajectoryStore
from wc.distributed import (LocalExecutor, RayExecutor, Unit, UnitsFailed, WorkerSpec, drive, every_unit,
                            open_executor, uses_cuda)
from wc.paths import RENDER, RENDER_PAIRS
from wc.render.config import RenderConfig
from wc.render.contact_sheet import write_contact_sheet
from wc.render.frames import RenderedStore, RenderedWriter
from wc.render.rig import render_cameras
from wc.render.worker import RenderBatch, RenderWorker
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import SceneConfig

SECTIONS = ["render", "scene"]
SOURCE, EXPANDED = RENDER_PAIRS


def default_pairs() -> list[tuple[str, str]]:
    """The source store, and the expanded store when the expand stage has written it."""
    return [SOURCE] + ([EXPANDED] if Path(EXPANDED[0]).exists() else [])


def select_episodes(store: TrajectoryStore, tasks: Sequence[str] | None) -> list[str]:
    """Ids of the store's accepted episodes to render: all, or those of the given tasks (error if none match;
    an empty store, e.g. an expansion that accepted nothing, renders to an empty frames store). Episodes kept
    for world-model training only (`accepted` false: validate.train_on_task_failures) are not rendered."""
    attrs = {e: store.episode_attrs(e) for e in store.episode_ids}
    ids = [e for e, a in attrs.items() if a["accepted"] is not False and (tasks is None or a["task"] in tasks)]
    if not ids and store.episode_ids:
        present = sorted({a["task"] for a in attrs.values()})
        raise ValueError(f"{store.path}: no episode to render (render.tasks {list(tasks or [])}; "
                         f"tasks in the store: {present})")
    return ids


class StoreRender:
    """One store's episodes as a stream of work units (wc.distributed.streams) of `per_unit` episodes each, written
    in episode order as they are filed."""

    def __init__(self, store: TrajectoryStore, ids: list[str], per_unit: int, worker: WorkerSpec,
                 writer: RenderedWriter, totals: dict[str, Any]) -> None:
        self.store, self.worker, self.writer, self.totals = store, worker, writer, totals
        self.chunks = deque(ids[i:i + per_unit] for i in range(0, len(ids), per_unit))
        self.filing: deque[list[str]] = deque()
        self.frames = 0
        self.bar = tqdm(total=len(ids), desc=f"render {store.path.name}", unit="episode")

    def next_unit(self) -> Unit | None:
        if not self.chunks:
            return None
        eids = self.chunks.popleft()
        self.filing.append(eids)
        return Unit(self.worker, (str(self.store.path.resolve()), eids),
                    f"render {self.store.path} episodes {eids[0]}..{eids[-1]}")

    def file(self, batch: RenderBatch) -> None:
        for eid, views in zip(self.filing.popleft(), batch.views):
            info = self.store.episode_attrs(eid)
            self.writer.add_episode(eid, views, {k: info.get(k) for k in ("task", "source", "split", "seed")})
            self.frames += self.store.num_frames(eid)
            self.bar.update(1)
        totals = self.totals
        totals["seconds"] = {n: totals["seconds"].get(n, 0.0) + t for n, t in batch.seconds.items()}
        totals["renderers_built"] += batch.renderers_built
        totals["device"], totals["environment"] = batch.device, batch.environment


def render_store(src: Path, out: Path, cfg: RenderConfig, executor: LocalExecutor | RayExecutor, worker: WorkerSpec,
                 cameras: list[str], phash: str, totals: dict[str, Any]) -> dict[str, Any]:
    """Render the selected episodes of one trajectory store into a rendered-frames store at `out` (nothing, if a
    unit kept failing); the render times and renderers built are added to `totals`."""
    if not src.exists():
        raise FileNotFoundError(f"trajectory store {src} not found: run the stage that writes it first "
                                "(simulate + validate for the source store, expand for the expanded one)")
    if src.resolve() == out.resolve():
        raise ValueError(f"render would overwrite its input {src}: choose another output path")
    store = TrajectoryStore(src)
    ids = select_episodes(store, cfg.tasks)
    attrs = {"trajectories": str(src), "params_hash": phash, "created_by": "stages.render",
             "trajectory_params_hash": store.attrs.get("params_hash"), "dt": store.dt}
    with RenderedWriter(out, cameras=cameras, width=cfg.width, height=cfg.height, fps=1.0 / store.dt,
                        attrs=attrs) as writer, every_unit(executor, "render"):
        stream = StoreRender(store, ids, cfg.episodes_per_unit, worker, writer, totals)
        with stream.bar:
            for _ in drive(executor, [stream], max(1, len(stream.chunks))):  # no unit depends on another
                pass
    return {"trajectories": str(src), "out": str(out), "episodes": len(ids), "frames": stream.frames}


def render(params: dict[str, Any], pairs: Sequence[tuple[str | Path, str | Path]] | None = None,
           report: str | Path = RENDER["report"], sheet: str | Path = RENDER["sheet"]) -> dict[str, Any]:
    """Render each (trajectory store, output store) pair (default: source, and expanded when present);
    write the report and a contact sheet of the first output. Returns the report. Ray units that kept failing:
    the report lists them, the store they belong to and later ones are not written, UnitsFailed."""
    cfg = load_section(params, "render", RenderConfig)
    scene_cfg = load_section(params, "scene", SceneConfig)
    try:
        cameras = render_cameras(scene_cfg.cameras, cfg.cameras, cfg.width, cfg.height)
    except ValueError as err:
        raise ParamsError(f"{params.get('_source', '<params>')}: {err}") from err
    pairs = [(Path(a), Path(b)) for a, b in (default_pairs() if pairs is None else pairs)]
    if not pairs:
        raise ValueError("render: no (trajectory store, output store) pair given")
    phash = params_hash(without_keys(params, "render", ("executor", "episodes_per_unit")), SECTIONS)
    if cfg.executor == "local":  # one renderer per layout for the whole run, as it always was
        local = RenderWorker(params)
        worker = WorkerSpec("render", lambda: local)
    else:
        worker = WorkerSpec(f"render:{secrets.token_hex(8)}", RenderWorker, (params,))
    totals: dict[str, Any] = {"seconds": {}, "renderers_built": 0, "device": cfg.device, "environment": None}
    started = time.perf_counter()
    outputs, failed = [], None
    with open_executor(cfg.executor, params, uses_cuda(cfg.device)) as executor:
        try:
            for src, out in pairs:
                outputs.append(render_store(src, out, cfg, executor, worker, list(cameras), phash, totals))
        except UnitsFailed as err:
            failed = err
    wall = time.perf_counter() - started
    frames = sum(o["frames"] for o in outputs)
    if failed is None:
        write_contact_sheet(RenderedStore(pairs[0][1]), sheet, cfg.sheet_frames, cfg.sheet_episodes)
    device, environment = ((totals["device"], totals["environment"] or environment_info("cpu"))
                           if cfg.executor != "local"  # ray, processes: where a unit ran, if one did
                           else (local.device, local.environment))
    result = {
        "outputs": outputs,
        "episodes": sum(o["episodes"] for o in outputs),
        "frames": frames,
        "cameras": list(cameras),
        "width": cfg.width,
        "height": cfg.height,
        "device": device,
        "ms_per_frame": {n: 1000.0 * totals["seconds"].get(n, 0.0) / frames if frames else None for n in cameras},
        "ms_per_frame_all_cameras_wall": 1000.0 * wall / frames if frames else None,
        "renderers_built": totals["renderers_built"],
        "contact_sheet": str(sheet),
        "executor": executor.report(),
        "params_hash": phash,
        "wall_s": wall,
        "environment": environment,
    }
    write_json_atomic(report, result)
    if failed is not None:
        raise failed
    return result


def pairs_problem(inputs: Sequence[str] | None, outs: Sequence[str] | None) -> str | None:
    """What is wrong with `--inputs` / `--outs` (None: nothing)."""
    if (inputs is None) != (outs is None) or (inputs and outs is not None and len(inputs) != len(outs)):
        return "--inputs and --outs go together, one output per input"
    return None


def render_inputs(params: dict[str, Any], report: str | Path = RENDER["report"], sheet: str | Path = RENDER["sheet"],
                  inputs: Sequence[str] | None = None, outs: Sequence[str] | None = None) -> dict[str, Any]:
    """`render` of the stores `inputs` into `outs`, one per input (None: the default pairs)."""
    return render(params, list(zip(inputs, outs)) if inputs and outs else None, report, sheet)


def render_summary(result: dict[str, Any]) -> str:
    """The line `python -m stages.render` prints."""
    speed = ", ".join(f"{n} {ms:.1f} ms" for n, ms in result["ms_per_frame"].items())
    return (f"render: {result['episodes']} episodes, {result['frames']} frames at {result['width']}x{result['height']} "
            f"on {result['device']} ({speed} per frame); {result['wall_s']:.1f} s; sheet {result['contact_sheet']}")
