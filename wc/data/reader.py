"""TrajectoryStore: the read-only view of a trajectory store (layout in wc/data/store.py)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from wc.data.chunks import read_rows
from wc.data.schema import (EPISODE_ARRAYS, ROOT_ATTRS, SCHEMA, SCHEMA_PREFIX, ObjectMesh, PrescribedSamples,
                            episode_sort_key)


class TrajectoryStore:
    """Read-only view of a trajectory store; small scene arrays load on first use, episodes per call."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"no trajectory store at {self.path}")
        try:
            self._root = zarr.open_group(self.path, mode="r", zarr_format=3)
        except (zarr.errors.BaseZarrError, FileNotFoundError, NotADirectoryError, ValueError, KeyError) as e:
            raise ValueError(f"{self.path} is not a worldcontact trajectory store (no zarr v3 group: {e})") from e
        self._attrs: dict[str, Any] = dict(self._root.attrs)
        schema = self._attrs.get("schema")
        if not isinstance(schema, str) or not schema.startswith(SCHEMA_PREFIX):
            raise ValueError(f"{self.path} is not a worldcontact trajectory store (schema attr {schema!r})")
        if schema != SCHEMA:
            raise ValueError(f"{self.path}: schema version mismatch, store has {schema!r}, this code reads {SCHEMA!r}")
        missing = [k for k in ROOT_ATTRS if k not in self._attrs]
        if missing:
            raise ValueError(f"{self.path}: corrupt trajectory store, root attrs {missing} missing "
                             "(was the writer interrupted?)")
        self._objects: dict[str, ObjectMesh] | None = None
        self._prescribed: dict[str, PrescribedSamples] | None = None
        self._episode_ids: list[str] | None = None
        self._episode_id_set: frozenset[str] | None = None
        self._episode_attrs: dict[str, dict[str, Any]] = {}
        self._arrays: dict[str, dict[str, zarr.Array]] = {}

    def __repr__(self) -> str:
        return f"TrajectoryStore({str(self.path)!r})"

    def _member(self, key: str) -> Any:
        try:
            return self._root[key]
        except (KeyError, FileNotFoundError) as e:
            raise ValueError(f"{self.path}: corrupt trajectory store, '{key}' is missing") from e

    # -- scene ------------------------------------------------------------------------------
    @property
    def attrs(self) -> dict[str, Any]:
        """Root attrs (schema, dt, substeps, units, created_by, params_hash, name lists)."""
        return dict(self._attrs)

    @property
    def dt(self) -> float:
        return float(self._attrs["dt"])

    @property
    def object_names(self) -> list[str]:
        return list(self._attrs["object_order"])

    @property
    def link_names(self) -> list[str]:
        return list(self._attrs["link_names"])

    @property
    def env_names(self) -> list[str]:
        return list(self._attrs["env_names"])

    @property
    def num_vertices(self) -> int:
        """N_total: rows of x / v of an episode holding every object."""
        return int(self._attrs["object_offsets"][-1])

    @property
    def objects(self) -> dict[str, ObjectMesh]:
        """Objects by name, in `object_names` order."""
        if self._objects is None:
            offs = self._attrs["object_offsets"]
            out = {}
            for i, name in enumerate(self.object_names):
                g = self._member(f"objects/{name}")
                arr = {k: np.asarray(self._member(f"objects/{name}/{k}")[...])
                       for k in ("rest_positions", "faces", "rest_uv", "vertex_area")}
                if arr["rest_positions"].shape[0] != offs[i + 1] - offs[i]:
                    raise ValueError(f"{self.path}: object '{name}' has {arr['rest_positions'].shape[0]} "
                                     f"vertices but object_offsets says {offs[i + 1] - offs[i]}")
                a = g.attrs
                out[name] = ObjectMesh(name=name, kind=a["kind"], tag=int(a["tag"]), material=dict(a["material"]),
                                       vertices=slice(offs[i], offs[i + 1]), **arr)
            self._objects = out
        return self._objects

    @property
    def prescribed(self) -> dict[str, PrescribedSamples]:
        """Prescribed sample sets by name, in insertion order."""
        if self._prescribed is None:
            out = {}
            for name in self._attrs["prescribed_order"]:
                a = self._member(f"prescribed/{name}").attrs
                out[name] = PrescribedSamples(
                    name=name, tag=int(a["tag"]), link=str(a["link"]),
                    local_points=np.asarray(self._member(f"prescribed/{name}/local_points")[...]),
                    local_normals=np.asarray(self._member(f"prescribed/{name}/local_normals")[...]))
            self._prescribed = out
        return self._prescribed

    # -- episodes ---------------------------------------------------------------------------
    @property
    def episode_ids(self) -> list[str]:
        """All episode ids, sorted."""
        if self._episode_ids is None:
            keys = [k for k in self._member("episodes").group_keys()]
            self._episode_ids = sorted(keys, key=episode_sort_key)
        return list(self._episode_ids)

    def _episode_set(self) -> frozenset[str]:
        if self._episode_id_set is None:
            self._episode_id_set = frozenset(self.episode_ids)
        return self._episode_id_set

    def _episode_group(self, eid: str) -> zarr.Group:
        if eid not in self._episode_set():
            raise KeyError(f"{self.path}: no episode {eid!r}")
        return self._member(f"episodes/{eid}")

    def episode_attrs(self, eid: str) -> dict[str, Any]:
        """Attrs of one episode (task, seed, cell, speed, amplitude, split, accepted, first_failure, source)."""
        if eid not in self._episode_attrs:
            self._episode_attrs[eid] = dict(self._episode_group(eid).attrs)
        return dict(self._episode_attrs[eid])

    def episodes_where(self, *, split: str | None = None, task: str | None = None,
                       accepted: bool | None = None, source: str | None = None) -> list[str]:
        """Sorted ids of episodes whose attrs equal every given (non-None) value."""
        want = {k: v for k, v in (("split", split), ("task", task), ("accepted", accepted), ("source", source))
                if v is not None}
        return [e for e in self.episode_ids
                if all(self.episode_attrs(e).get(k) == v for k, v in want.items())]

    def episode_objects(self, eid: str) -> list[str]:
        """Objects present in an episode (rows of its x, in this order); all objects unless it says."""
        return list(self.episode_attrs(eid).get("objects", self.object_names))

    def episode_links(self, eid: str) -> list[str]:
        """Columns of an episode's link_poses; all link_names unless it says."""
        return list(self.episode_attrs(eid).get("links", self.link_names))

    def episode_layout(self, eid: str) -> dict[str, slice]:
        """Rows of each present object in the episode's x / v."""
        return self.object_layout(self.episode_objects(eid))

    def object_layout(self, objects: Sequence[str]) -> dict[str, slice]:
        """Rows of each of `objects` in an x / v holding these objects in this order."""
        out, start = {}, 0
        for name in objects:
            n = self.objects[name].rest_positions.shape[0]
            out[name] = slice(start, start + n)
            start += n
        return out

    def _episode_arrays(self, eid: str) -> dict[str, zarr.Array]:
        if eid not in self._arrays:
            self._episode_group(eid)  # KeyError for unknown ids
            arrs = {k: self._member(f"episodes/{eid}/{k}") for k in EPISODE_ARRAYS}
            T = arrs["x"].shape[0]
            n = sum(s.stop - s.start for s in self.episode_layout(eid).values())
            bad = {k: a.shape for k, a in arrs.items() if a.shape[0] != T}
            if bad or arrs["x"].shape[1] != n or arrs["link_poses"].shape[1] != len(self.episode_links(eid)):
                raise ValueError(f"{self.path}: corrupt episode {eid}: inconsistent shapes "
                                 f"{ {k: a.shape for k, a in arrs.items()} } (N {n}, links {self.episode_links(eid)})")
            self._arrays[eid] = arrs
        return self._arrays[eid]

    def num_frames(self, eid: str) -> int:
        """T of one episode."""
        return int(self._episode_arrays(eid)["x"].shape[0])

    def chunk_frames(self, eid: str) -> int:
        """Frames per chunk along T of an episode's arrays."""
        return int(self._episode_arrays(eid)["x"].chunks[0])

    def _read(self, eid: str, sl: slice, fields: Sequence[str]) -> dict[str, np.ndarray]:
        arrs = self._episode_arrays(eid)
        out = {}
        for k in fields:
            if k not in arrs:
                raise KeyError(f"unknown episode array {k!r}; choose from {EPISODE_ARRAYS}")
            a = read_rows(arrs[k], sl.start, sl.stop, f"{self.path}: corrupt episode {eid}, array '{k}'", "frames")
            if not np.isfinite(a).all():  # written finite, so NaN = fill value of a missing chunk
                raise ValueError(f"{self.path}: corrupt episode {eid}: array '{k}' has non-finite values "
                                 f"in frames [{sl.start}, {sl.stop}) (missing chunk?)")
            out[k] = a
        return out

    def read_episode(self, eid: str, fields: Sequence[str] = EPISODE_ARRAYS) -> dict[str, np.ndarray]:
        """Whole episode: {x, v (T, N_e, 3), action (T, 14), link_poses (T, L_e, 7), env_poses (T, E, 7)}."""
        return self._read(eid, slice(0, self.num_frames(eid)), fields)

    def read_window(self, eid: str, start: int, length: int,
                    fields: Sequence[str] = EPISODE_ARRAYS) -> dict[str, np.ndarray]:
        """Frames [start, start + length) of an episode, reading only the chunks that hold them."""
        T = self.num_frames(eid)
        if length < 1 or start < 0 or start + length > T:
            raise IndexError(f"window [{start}, {start + length}) is out of range for episode {eid} "
                             f"with {T} frames")
        return self._read(eid, slice(start, start + length), fields)
