"""The render stage: trajectory stores -> rendered-frames stores (top and wrist RGB views per frame),
a JSON report and a contact sheet PNG.

Every selected episode is rendered at the trajectory's frame rate (one image per stored frame, fps =
1 / dt) by Newton's SensorCamera (wc.render.renderer). Outputs are written atomically; a missing input
store, a camera link an episode lacks, or a task filter that matches nothing fails with a clear error.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from wc.config import ParamsError, load_section, params_hash
from wc.data.store import TrajectoryStore
from wc.devices import resolve_warp_device
from wc.paths import RENDER, RENDER_PAIRS
from wc.render.config import RenderConfig
from wc.render.contact_sheet import write_contact_sheet
from wc.render.frames import RenderedStore, RenderedWriter
from wc.render.geometry import episode_geometry
from wc.render.renderer import EpisodeRenderer
from wc.render.rig import check_camera_links, render_cameras
from wc.reports import environment_info, write_json_atomic
from wc.scene.config import CameraConfig, SceneConfig

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


class _Renderers:
    """One EpisodeRenderer per geometry layout, shared by every store of the run."""

    def __init__(self, cameras: dict[str, CameraConfig], device: str, cfg: RenderConfig) -> None:
        self.cameras, self.device, self.cfg = cameras, device, cfg
        self.by_layout: dict[tuple, EpisodeRenderer] = {}

    def frames(self, store: TrajectoryStore, eid: str, scene_cfg: SceneConfig) -> dict[str, np.ndarray]:
        where = f"{store.path}: episode {eid}"
        geometry = episode_geometry(store, eid, scene_cfg)
        check_camera_links(self.cameras, geometry.link_names, where)
        renderer = self.by_layout.get(geometry.layout)
        if renderer is None:
            renderer = EpisodeRenderer(geometry, self.cameras, self.device, self.cfg.frames_per_batch, self.cfg.shadows)
            self.by_layout[geometry.layout] = renderer
        a = store.read_episode(eid, ("x", "link_poses"))
        return renderer.render(a["x"], a["link_poses"], where)

    def seconds(self) -> dict[str, float]:
        return {n: sum(r.seconds[n] for r in self.by_layout.values()) for n in self.cameras}


def render_store(src: Path, out: Path, scene_cfg: SceneConfig, cfg: RenderConfig, renderers: _Renderers,
                 phash: str) -> dict[str, Any]:
    """Render the selected episodes of one trajectory store into a rendered-frames store at `out`."""
    if not src.exists():
        raise FileNotFoundError(f"trajectory store {src} not found: run the stage that writes it first "
                                "(simulate + validate for the source store, expand for the expanded one)")
    if src.resolve() == out.resolve():
        raise ValueError(f"render would overwrite its input {src}: choose another output path")
    store = TrajectoryStore(src)
    ids = select_episodes(store, cfg.tasks)
    frames = 0
    attrs = {"trajectories": str(src), "params_hash": phash, "created_by": "stages.render",
             "trajectory_params_hash": store.attrs.get("params_hash"), "dt": store.dt}
    with RenderedWriter(out, cameras=list(renderers.cameras), width=cfg.width, height=cfg.height,
                        fps=1.0 / store.dt, attrs=attrs) as writer:
        for eid in tqdm(ids, desc=f"render {src.name}", unit="episode"):
            views = renderers.frames(store, eid, scene_cfg)
            info = store.episode_attrs(eid)
            writer.add_episode(eid, views, {k: info.get(k) for k in ("task", "source", "split", "seed")})
            frames += store.num_frames(eid)
    return {"trajectories": str(src), "out": str(out), "episodes": len(ids), "frames": frames}


def render(params: dict[str, Any], pairs: Sequence[tuple[str | Path, str | Path]] | None = None,
           report: str | Path = RENDER["report"], sheet: str | Path = RENDER["sheet"]) -> dict[str, Any]:
    """Render each (trajectory store, output store) pair (default: source, and expanded when present);
    write the report and a contact sheet of the first output. Returns the report."""
    cfg = load_section(params, "render", RenderConfig)
    scene_cfg = load_section(params, "scene", SceneConfig)
    try:
        cameras = render_cameras(scene_cfg.cameras, cfg.cameras, cfg.width, cfg.height)
    except ValueError as err:
        raise ParamsError(f"{params.get('_source', '<params>')}: {err}") from err
    pairs = [(Path(a), Path(b)) for a, b in (default_pairs() if pairs is None else pairs)]
    if not pairs:
        raise ValueError("render: no (trajectory store, output store) pair given")
    device = resolve_warp_device(cfg.device, "render.device")
    phash = params_hash(params, SECTIONS)
    renderers = _Renderers(cameras, device, cfg)
    started = time.perf_counter()
    outputs = [render_store(src, out, scene_cfg, cfg, renderers, phash) for src, out in pairs]
    wall = time.perf_counter() - started
    frames = sum(o["frames"] for o in outputs)
    write_contact_sheet(RenderedStore(pairs[0][1]), sheet, cfg.sheet_frames, cfg.sheet_episodes)
    result = {
        "outputs": outputs,
        "episodes": sum(o["episodes"] for o in outputs),
        "frames": frames,
        "cameras": list(cameras),
        "width": cfg.width,
        "height": cfg.height,
        "device": device,
        "ms_per_frame": {n: 1000.0 * s / frames if frames else None for n, s in renderers.seconds().items()},
        "ms_per_frame_all_cameras_wall": 1000.0 * wall / frames if frames else None,
        "renderers_built": len(renderers.by_layout),
        "contact_sheet": str(sheet),
        "params_hash": phash,
        "wall_s": wall,
        "environment": environment_info(device),
    }
    write_json_atomic(report, result)
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
