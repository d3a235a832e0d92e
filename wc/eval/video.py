"""Side-by-side video of one stress episode: ground truth | WorldContact | the best baseline, rendered with the
render stage's renderer (Newton SensorCamera, wc.render.renderer) from one camera (top by default).

The best baseline is the one of stress.video.baselines with the lowest held-out position MSE in the evaluate
stage's metrics (reports/metrics.json); without that file (or none of them in it) the lowest position MSE on
the video case itself decides, and the report says which. A diverged prediction holds its last finite frame
and its panel says from which step. Writes an mp4 (OpenCV mp4v, wc.policy_eval.videos.write_mp4) at 1 / dt
frames per second and a contact-sheet PNG (three labelled rows, a few evenly spaced frames) for people
without a video player.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from wc.data.store import TrajectoryStore
from wc.devices import resolve_warp_device
from wc.eval.stress_config import StressConfig
from wc.policy_eval.videos import write_mp4
from wc.render.contact_sheet import sheet_frame_indices
from wc.render.geometry import episode_geometry
from wc.render.renderer import EpisodeRenderer
from wc.render.rig import render_cameras
from wc.reports import pyplot, save_figure_atomic
from wc.scene.config import SceneConfig

GROUND_TRUTH_LABEL = "ground truth (Newton)"
FRAMES_PER_BATCH = 8


class EpisodeRollout(Protocol):
    def full_x(self, store: TrajectoryStore) -> np.ndarray:
        """(S, N_e, 3) predicted x of frames 1..S in the episode's row layout."""
        ...


def best_baseline(candidates: Sequence[str], available: Sequence[str], metrics: str | Path,
                  case_mse: Mapping[str, float | None]) -> tuple[str, float, str]:
    """(name, position MSE [m^2], where the MSE comes from) of the candidate with the lowest position MSE:
    the evaluate metrics file's held-out MSE, else `case_mse` (this stress case's)."""
    present = [c for c in candidates if c in available]
    if not present:
        raise ValueError(f"stress.video.baselines {list(candidates)}: none is an available method ({list(available)})")
    path = Path(metrics)
    if path.is_file():
        methods = json.loads(path.read_text()).get("methods", {})
        scored = {c: methods[c]["position_mse_m2"] for c in present
                  if c in methods and methods[c].get("position_mse_m2") is not None}
        if scored:
            name = min(scored, key=scored.__getitem__)
            return name, float(scored[name]), f"{path} (held-out position MSE)"
    scored = {c: case_mse[c] for c in present if case_mse.get(c) is not None}
    if not scored:
        raise ValueError(f"stress.video.baselines {present}: no position MSE in {path} nor on the video case "
                         "(every one diverged)")
    name = min(scored, key=scored.__getitem__)
    return name, float(scored[name]), "this stress case's position MSE (no evaluate metrics for these methods)"


def hold_finite(x: np.ndarray) -> tuple[np.ndarray, int | None]:
    """x (T, N, 3) with every frame from the first non-finite one on replaced by the last finite frame, and
    that first non-finite frame's index (None: all finite). Frame 0 must be finite."""
    ok = np.isfinite(x).all(axis=(1, 2))
    if not ok[0]:
        raise ValueError("frame 0 is not finite")
    bad = np.flatnonzero(~ok)
    if not len(bad):
        return x, None
    out = x.copy()
    out[bad[0]:] = x[bad[0] - 1]
    return out, int(bad[0])


def label_frames(frames: np.ndarray, lines: Sequence[str], dt: float | None = None) -> np.ndarray:
    """A copy of RGB frames (T, H, W, 3) uint8 with `lines` of text in the top-left corner (black on a white
    halo), and each frame's time k * dt [s] below them when dt is given."""
    out = frames.copy()
    scale = max(0.3, frames.shape[2] / 400.0)
    step = int(round(28 * scale)) + 2
    for k, frame in enumerate(out):
        for i, line in enumerate([*lines, *([f"t = {k * dt:.2f} s"] if dt is not None else [])]):
            origin = (3, step * (i + 1) - 2)
            cv2.putText(frame, line, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 2, cv2.LINE_AA)
            cv2.putText(frame, line, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
    return out


def side_by_side(panels: Sequence[np.ndarray]) -> np.ndarray:
    """(T, H, sum W, 3): the panels (T, H, W_i, 3) next to each other, left to right."""
    if len({p.shape[:2] for p in panels}) != 1:
        raise ValueError(f"panels need the same frame count and height, got {[p.shape for p in panels]}")
    return np.concatenate(list(panels), axis=2)


def write_sheet(panels: Sequence[np.ndarray], labels: Sequence[str], path: str | Path, count: int, dt: float) -> Path:
    """Contact sheet: one row per panel (T, H, W, 3), `count` evenly spaced frames, rows labelled (PNG)."""
    plt = pyplot()
    ks = sheet_frame_indices(len(panels[0]), count)
    fig, axes = plt.subplots(len(panels), len(ks), figsize=(1.6 * len(ks) + 0.4, 1.6 * len(panels) + 0.4),
                             squeeze=False, constrained_layout=True)
    for i, (frames, label) in enumerate(zip(panels, labels)):
        for j, k in enumerate(ks):
            ax = axes[i, j]
            ax.imshow(frames[k], interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"t = {k * dt:.2f} s", fontsize=8)
        axes[i, 0].set_ylabel(label, fontsize=8)
    return save_figure_atomic(fig, path)


def side_by_side_video(store: TrajectoryStore, scene_cfg: SceneConfig, cfg: StressConfig,
                       rollouts: Mapping[tuple[str, str], EpisodeRollout], rows: Sequence[Mapping[str, Any]],
                       metrics: str | Path, video: str | Path, sheet: str | Path) -> dict[str, Any]:
    """Render the first episode of stress.video.case as ground truth | video.method | the best baseline;
    write the mp4 and the contact sheet; return what was shown."""
    v = cfg.video
    episodes = [e for e in store.episode_ids if store.episode_attrs(e).get("case") == v.case]
    if not episodes:
        raise ValueError(f"{store.path}: no episode of stress case {v.case!r} to put in the video")
    eid = episodes[0]
    methods = sorted({m for e, m in rollouts if e == eid})
    case_mse = {r["method"]: r["position_mse_m2"] for r in rows if r["case"] == v.case}
    baseline, baseline_mse, chosen_by = best_baseline(v.baselines, methods, metrics, case_mse)
    recorded = store.read_episode(eid, ("x", "link_poses"))
    frames = min(v.frames, len(recorded["x"]))
    sequences, labels = [recorded["x"][:frames].astype(np.float64)], [GROUND_TRUTH_LABEL]
    diverged = {}
    for name in (v.method, baseline):
        predicted = rollouts[(eid, name)].full_x(store)[:frames - 1]
        x, first_bad = hold_finite(np.concatenate([sequences[0][:1], predicted]))
        sequences.append(x)
        diverged[name] = first_bad
        labels.append(name if name == v.method else f"{name} (best baseline)")
    camera = render_cameras(scene_cfg.cameras, [v.camera], v.panel_px, v.panel_px)
    device = resolve_warp_device(v.device, "evaluate.video.device")
    renderer = EpisodeRenderer(episode_geometry(store, eid, scene_cfg), camera, device, FRAMES_PER_BATCH, shadows=True)
    poses = recorded["link_poses"][:frames]
    rendered = renderer.render(np.concatenate(sequences), np.concatenate([poses] * len(sequences)),
                               f"{store.path}: episode {eid}")[v.camera]
    dt = float(store.dt)
    panels = []
    for i, label in enumerate(labels):
        part = rendered[i * frames:(i + 1) * frames]
        name = (None, v.method, baseline)[i]
        lines = [label] + ([f"diverged at step {diverged[name]}"] if name and diverged[name] is not None else [])
        panels.append(label_frames(part, lines, dt))
    write_mp4(video, list(side_by_side(panels)), fps=1.0 / dt)
    write_sheet(panels, labels, sheet, v.sheet_frames, dt)
    return {"case": v.case, "episode": eid, "frames": frames, "fps": 1.0 / dt, "panel_px": v.panel_px,
            "camera": v.camera, "panels": labels, "method": v.method, "baseline": baseline,
            "baseline_position_mse_m2": baseline_mse, "baseline_chosen_by": chosen_by,
            "diverged_at_frame": diverged, "video": str(video), "sheet": str(sheet)}
