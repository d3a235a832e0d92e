"""The rendered-frames store (Zarr v3): uint8 RGB frames per episode and camera.

    <name>.zarr/
      attrs: {schema: "worldcontact-rendered/1", cameras: [top, wrist], width, height, fps,
              trajectories: <path of the trajectory store rendered>, params_hash, created_by}
      episodes/<episode_id>/<camera>  (T, H, W, 3) uint8, one chunk per frame
      episodes/<episode_id>.attrs: {task, source, frames}

Episode ids and frame counts match the trajectory store: frame k of the camera array is the
view at t = k·dt. Written atomically: a temporary sibling renamed into place on success.
"""

from __future__ import annotations

import os
import secrets
import shutil
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import zarr

from wc.atomic import remove_stale_temporaries
from wc.data.chunks import read_rows
from wc.reports import replace_dir

RENDERED_SCHEMA = "worldcontact-rendered/1"


class RenderedWriter:
    """``with RenderedWriter(path, cameras=..., width=..., height=..., fps=...) as w: w.add_episode(eid, frames)``."""

    def __init__(self, path: str | os.PathLike[str], *, cameras: Sequence[str], width: int, height: int, fps: float,
                 attrs: dict[str, Any] | None = None) -> None:
        if not cameras or len(set(cameras)) != len(cameras):
            raise ValueError(f"cameras must be distinct names, got {list(cameras)}")
        if width < 1 or height < 1 or not fps > 0:
            raise ValueError(f"width, height and fps must be positive, got {width}, {height}, {fps}")
        self.path = Path(path)
        self.cameras = list(cameras)
        self.shape = (int(height), int(width), 3)
        self._attrs = {"schema": RENDERED_SCHEMA, "cameras": self.cameras, "width": int(width),
                       "height": int(height), "fps": float(fps), **(attrs or {})}
        self._tmp: Path | None = None
        self._root: zarr.Group | None = None

    def __enter__(self) -> RenderedWriter:
        if self.path.exists() and not (self.path / "zarr.json").is_file():
            raise FileExistsError(f"{self.path} exists and is not a zarr store; refusing to replace it")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(self.path)
        self._tmp = self.path.with_name(f"{self.path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
        self._root = zarr.open_group(self._tmp, mode="w", zarr_format=3)
        self._root.attrs.update(self._attrs)
        self._root.create_group("episodes")
        return self

    def add_episode(self, episode_id: str, frames: dict[str, np.ndarray], attrs: dict[str, Any] | None = None) -> None:
        """frames: camera -> (T, H, W, 3) uint8, every camera of the store, equal T."""
        assert self._root is not None, "use RenderedWriter as a context manager"
        if set(frames) != set(self.cameras):
            raise ValueError(f"episode {episode_id}: cameras {sorted(frames)} != store cameras {sorted(self.cameras)}")
        lengths = {cam: len(a) for cam, a in frames.items()}
        if len(set(lengths.values())) != 1 or min(lengths.values()) < 1:
            raise ValueError(f"episode {episode_id}: cameras need the same, non-zero frame count, got {lengths}")
        group = self._root["episodes"].create_group(episode_id)
        for cam, a in frames.items():
            a = np.asarray(a)
            if a.dtype != np.uint8 or a.shape[1:] != self.shape:
                raise ValueError(f"episode {episode_id} camera {cam}: need uint8 (T, {', '.join(map(str, self.shape))}), "
                                 f"got {a.dtype} {a.shape}")
            arr = group.create_array(cam, shape=a.shape, dtype=np.uint8, chunks=(1, *self.shape))
            arr[...] = a
        group.attrs.update({**(attrs or {}), "frames": int(next(iter(lengths.values())))})

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        tmp, self._tmp, self._root = self._tmp, None, None
        if exc_type is not None:
            shutil.rmtree(tmp, ignore_errors=True)
            return
        replace_dir(tmp, self.path)


class RenderedStore:
    """Read a rendered-frames store."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if not (self.path / "zarr.json").is_file():
            raise FileNotFoundError(f"{self.path}: no rendered-frames store (run the render stage)")
        self._root = zarr.open_group(self.path, mode="r")
        schema = self._root.attrs.get("schema")
        if schema != RENDERED_SCHEMA:
            raise ValueError(f"{self.path}: schema {schema!r}, expected {RENDERED_SCHEMA!r}")

    @property
    def attrs(self) -> dict[str, Any]:
        return dict(self._root.attrs)

    @property
    def cameras(self) -> list[str]:
        return list(self._root.attrs["cameras"])

    def episode_ids(self) -> list[str]:
        return sorted(self._root["episodes"].group_keys())

    def episode_attrs(self, episode_id: str) -> dict[str, Any]:
        return dict(self._episode(episode_id).attrs)

    def frames(self, episode_id: str, camera: str, start: int = 0, stop: int | None = None) -> np.ndarray:
        """(T', H, W, 3) uint8 frames [start, stop) of one camera."""
        if camera not in self.cameras:
            raise KeyError(f"{self.path}: no camera {camera!r}; cameras: {self.cameras}")
        array = self._episode(episode_id)[camera]
        stop = array.shape[0] if stop is None else stop
        return read_rows(array, start, stop, f"{self.path}: corrupt episode {episode_id}, camera '{camera}'", "frames")

    def _episode(self, episode_id: str) -> zarr.Group:
        try:
            return self._root["episodes"][episode_id]
        except KeyError:
            raise KeyError(f"{self.path}: no episode {episode_id!r}") from None
