"""A contact sheet of rendered frames for a person to look at: one row per (episode, camera), a few
evenly spaced frames per row, labelled with the episode, task, camera and frame index."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wc.render.frames import RenderedStore
from wc.reports import pyplot, save_figure_atomic

GAP_PX = 2


def sheet_frame_indices(frames: int, count: int) -> np.ndarray:
    """`count` frame indices evenly spaced over [0, frames - 1], first and last included (fewer if short)."""
    return np.unique(np.linspace(0, frames - 1, min(count, frames)).round().astype(int))


def contact_sheet_image(store: RenderedStore, frames_per_row: int, max_episodes: int) -> tuple[np.ndarray, list[str]]:
    """(H, W, 3) uint8 mosaic and one label per row, rows = first `max_episodes` episodes x cameras."""
    attrs = store.attrs
    h, w = attrs["height"], attrs["width"]
    rows, labels = [], []
    for eid in store.episode_ids()[:max_episodes]:
        info = store.episode_attrs(eid)
        ks = sheet_frame_indices(info["frames"], frames_per_row)
        for cam in store.cameras:
            row = np.full((h, frames_per_row * (w + GAP_PX), 3), 255, np.uint8)
            for j, k in enumerate(ks):
                row[:, j * (w + GAP_PX): j * (w + GAP_PX) + w] = store.frames(eid, cam, int(k), int(k) + 1)[0]
            rows.append(np.concatenate([row, np.full((GAP_PX, row.shape[1], 3), 255, np.uint8)]))
            labels.append(f"{eid} {info.get('task', '')}\n{cam}, frames {', '.join(map(str, ks))}")
    if not rows:
        raise ValueError(f"{store.path}: no episodes to put on a contact sheet")
    return np.concatenate(rows), labels


def write_contact_sheet(store: RenderedStore, path: str | Path, frames_per_row: int, max_episodes: int) -> Path:
    """Save the contact sheet PNG at `path` (atomically)."""
    image, labels = contact_sheet_image(store, frames_per_row, max_episodes)
    plt = pyplot()
    row_h = image.shape[0] / len(labels)
    scale = 1.0 / 100.0  # 1 px of the mosaic = 1 px of the PNG at 100 dpi, plus a label column
    label_in = 2.2
    fig = plt.figure(figsize=(image.shape[1] * scale + label_in, image.shape[0] * scale + 0.3), dpi=100)
    ax = fig.add_axes((label_in / fig.get_figwidth(), 0.0, 1.0 - label_in / fig.get_figwidth(),
                       image.shape[0] * scale / fig.get_figheight()))
    ax.imshow(image, interpolation="nearest")
    ax.set_axis_off()
    for i, label in enumerate(labels):
        ax.text(-8, (i + 0.5) * row_h, label, ha="right", va="center", fontsize=7)
    fig.suptitle(f"{Path(store.path).name}: {store.attrs['width']}x{store.attrs['height']} px", fontsize=8,
                 y=1.0 - 0.05 / fig.get_figheight())
    return save_figure_atomic(fig, path)
