"""Trajectory store schema: names, array shapes and attrs of `worldcontact-trajectories/1` (layout in
wc/data/store.py), the checks every writer applies, and the scene records a reader returns."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr
from zarr.codecs import ZstdCodec

SCHEMA = "worldcontact-trajectories/1"
SCHEMA_PREFIX = "worldcontact-trajectories/"
EPISODE_ARRAYS = ("x", "v", "action", "link_poses", "env_poses")
EPISODE_ATTRS = ("task", "seed", "cell", "speed", "amplitude", "split", "accepted", "first_failure", "source")
LAYOUT_ATTRS = ("objects", "links")  # optional per-episode subsets of object_order / link_names
SPLITS = ("train", "val", "test", None)
SOURCES = ("simulator", "worldcontact")
KINDS = ("cloth", "rigid")
ACTION_DIM = 14  # [q_L 6, d_L, q_R 6, d_R]
POSE_DIM = 7  # pos 3, quat xyzw 4
ROOT_ATTRS = ("schema", "dt", "substeps", "units", "created_by", "params_hash",
              "object_order", "object_offsets", "prescribed_order", "link_names", "env_names")

_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
EPISODE_RE = re.compile(r"^ep_\d{6,}$")
_ZSTD = ZstdCodec(level=3)


def format_episode_id(index: int) -> str:
    """Episode id for an index: ``ep_000042`` (sorts lexicographically up to 10^6 episodes)."""
    return f"ep_{index:06d}"


def episode_sort_key(eid: str) -> tuple[int, str]:
    return (len(eid), eid)


def check_name(what: str, name: str) -> None:
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ValueError(f"invalid {what} name {name!r}: use letters, digits, '_', '.', '-'")


def jsonable(value: Any, where: str) -> Any:
    """Value converted to plain JSON types (numpy scalars/arrays, tuples); error names `where`."""
    if isinstance(value, np.generic):
        value = value.item()
    elif isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ValueError(f"{where}: dict key {k!r} is not a string")
            out[k] = jsonable(v, f"{where}.{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [jsonable(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{where}: non-finite value {value!r} is not allowed in attrs")
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise ValueError(f"{where}: value {value!r} of type {type(value).__name__} is not JSON-serialisable")


def as_array(name: str, a: Any, dtype: type, where: str) -> np.ndarray:
    """`a` as a C-contiguous array of `dtype`, refusing lossy kinds (e.g. float -> int, str -> float)."""
    arr = np.asarray(a)
    if not np.can_cast(arr.dtype, dtype, casting="same_kind"):
        raise TypeError(f"{where}: array '{name}' has dtype {arr.dtype}, not castable to {np.dtype(dtype)}")
    return np.ascontiguousarray(arr, dtype=dtype)


def check_shape(name: str, arr: np.ndarray, shape: tuple[int | None, ...], where: str) -> None:
    ok = arr.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, arr.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{where}: array '{name}' has shape {arr.shape}, expected {want}")


def subsequence(names: Any, full: Sequence[str], what: str, where: str) -> list[str]:
    """`names` as a list, checked to be a non-repeating subsequence of `full` in its order."""
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise TypeError(f"{where}: attr '{what}' must be a list of names, got {names!r}")
    unknown = [n for n in names if n not in full]
    if unknown:
        raise ValueError(f"{where}: attr '{what}' names {unknown}, not in the store's {list(full)}")
    if list(names) != [n for n in full if n in names]:
        raise ValueError(f"{where}: attr '{what}' {list(names)} must follow the store's order {list(full)}")
    return list(names)


def check_finite(name: str, arr: np.ndarray, where: str) -> None:
    """Raise if `arr` has NaN/Inf, naming the first bad index along axis 0 (the frame for episodes)."""
    if arr.size and not np.isfinite(arr).all():
        bad = int(np.argmax(~np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1)))
        raise ValueError(f"{where}: array '{name}' has non-finite values (NaN/Inf), first at index {bad}")


def _chunks(shape: tuple[int, ...], first: int | None = None) -> tuple[int, ...]:
    c = [max(1, d) for d in shape]
    if first is not None:
        c[0] = max(1, min(first, shape[0]))
    return tuple(c)


def write_array(group: zarr.Group, name: str, arr: np.ndarray, chunk_frames: int | None = None) -> None:
    fill = -1 if arr.dtype.kind == "i" else np.nan
    group.create_array(name, data=arr, chunks=_chunks(arr.shape, chunk_frames), compressors=_ZSTD, fill_value=fill)


@dataclass(frozen=True)
class ObjectMesh:
    """A simulated object: rest mesh (m), rest (u, v), lumped vertex area (m^2), and its rows in x."""

    name: str
    rest_positions: np.ndarray  # (N, 3) float32
    faces: np.ndarray  # (F, 3) int32
    rest_uv: np.ndarray  # (N, 2) float32
    vertex_area: np.ndarray  # (N,) float32
    kind: str  # cloth | rigid
    tag: int
    material: dict[str, Any]
    vertices: slice  # rows of this object in x of an episode holding every object (see episode_layout)


@dataclass(frozen=True)
class PrescribedSamples:
    """Sample set on a prescribed body, in the frame of `link` (a link_names or env_names entry)."""

    name: str
    local_points: np.ndarray  # (M, 3) float32, m
    local_normals: np.ndarray  # (M, 3) float32
    tag: int
    link: str
