"""Training windows with their frames resident on the training device: a batch is gathered by index.

Every phase that holds a training window is read from the store once; a layout's phases are concatenated
along the frame axis, so a window is one start frame and a batch of windows is one index gather on the device
(no per-step zarr reads or host copies of frames).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from wc.data.store import TrajectoryStore
from wc.train.data import LayoutKey, Phase, Window, read_phase_window


@dataclass
class LayoutFrames:
    """The frames of one layout's phases, concatenated: x, v (F, N, 3), poses (F, P, 7), on the device."""

    key: LayoutKey
    x: torch.Tensor
    v: torch.Tensor
    poses: torch.Tensor

    def gather(self, starts: torch.Tensor, length: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x, v (B, W, N, 3) and poses (B, W, P, 7) of the windows starting at frames `starts` (B,) (device)."""
        frames = starts[:, None] + torch.arange(length, device=starts.device)
        return self.x[frames], self.v[frames], self.poses[frames]

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.x, self.v, self.poses))


class ResidentWindows:
    """The training windows' frames on `device`, per layout; windows addressed as (layout index, start frame).

    layout_keys follow the windows' first appearance (as `WindowDataset.layout_keys`).
    """

    def __init__(self, store: TrajectoryStore, windows: list[Window], length: int, device: torch.device) -> None:
        if not windows:
            raise ValueError(f"{store.path}: no {length}-frame training window")
        self.length = length
        self.layout_keys: list[LayoutKey] = list(dict.fromkeys(w.phase.layout for w in windows))
        layout_index = {k: i for i, k in enumerate(self.layout_keys)}
        offsets: dict[Phase, int] = {}
        parts: list[list[dict[str, np.ndarray]]] = [[] for _ in self.layout_keys]
        sizes = [0] * len(self.layout_keys)
        for w in windows:  # each phase read once, in window order
            if w.phase not in offsets:
                li = layout_index[w.phase.layout]
                offsets[w.phase] = sizes[li]
                parts[li].append(read_phase_window(store, w.phase, w.phase.start, w.phase.stop - w.phase.start))
                sizes[li] += w.phase.stop - w.phase.start
        self.layouts = [LayoutFrames(key, *(torch.from_numpy(np.concatenate([p[name] for p in layout_parts]))
                                            .to(device) for name in ("x", "v", "poses")))
                        for key, layout_parts in zip(self.layout_keys, parts)]
        self.window_layout = np.array([layout_index[w.phase.layout] for w in windows], dtype=np.int64)
        self.window_start = np.array([offsets[w.phase] + w.start - w.phase.start for w in windows], dtype=np.int64)

    def batch_location(self, indices: list[int]) -> tuple[int, np.ndarray]:
        """(layout index, start frames (B,)) of a batch of window indices, all of one layout."""
        layouts = self.window_layout[indices]
        if not (layouts == layouts[0]).all():
            raise ValueError(f"a batch must hold windows of one layout, got layouts {sorted(set(layouts.tolist()))}")
        return int(layouts[0]), self.window_start[indices]

    @property
    def nbytes(self) -> int:
        return sum(f.nbytes for f in self.layouts)
