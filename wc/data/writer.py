"""TrajectoryWriter: a trajectory store written episode by episode, atomically (layout in wc/data/store.py)."""

from __future__ import annotations

import math
import os
import secrets
import shutil
from concurrent.futures import Future, ProcessPoolExecutor
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr

from wc.atomic import remove_stale_temporaries
from wc.data.schema import (ACTION_DIM, EPISODE_ARRAYS, EPISODE_ATTRS, EPISODE_RE, KINDS, POSE_DIM, SCHEMA, SOURCES,
                            SPLITS, as_array, check_finite, check_name, check_shape, format_episode_id, jsonable,
                            subsequence, write_array)
from wc.worker_pool import spawn_pool

if TYPE_CHECKING:
    from wc.scene.scene import Scene


class TrajectoryWriter:
    """Write a trajectory store episode by episode; atomic on success, nothing left on failure.

    Use as ``with TrajectoryWriter(path, ...) as w:``. Data goes to ``<path>.tmp-<pid>-<hex>``
    and is renamed to `path` on a clean exit (an existing store at `path` is replaced); on an
    exception the temporary directory is removed (one a killed writer left is removed when the next one
    starts: wc.atomic). Call `add_object` for every name in
    `object_order` before the first `add_episode`. write_processes > 0: episodes are checked here and their arrays
    written by that many spawned processes (zarr's writes hold the interpreter: a caller with other work keeps it),
    all finished before the store is renamed into place; the same store as written here.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        dt: float,
        substeps: int,
        params_hash: str,
        created_by: str,
        object_order: Sequence[str],
        link_names: Sequence[str],
        env_names: Sequence[str],
        chunk_frames: int = 16,
        units: str = "m, s",
        write_processes: int = 0,
    ) -> None:
        self.path = Path(path)
        if not (isinstance(write_processes, (int, np.integer)) and write_processes >= 0):
            raise ValueError(f"write_processes must be an int >= 0, got {write_processes!r}")
        self.write_processes = int(write_processes)
        self._pool: ProcessPoolExecutor | None = None
        self._pending: list[Future[None]] = []
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a positive finite number of seconds, got {dt!r}")
        if not (isinstance(substeps, (int, np.integer)) and substeps >= 1):
            raise ValueError(f"substeps must be a positive int, got {substeps!r}")
        if not (isinstance(chunk_frames, (int, np.integer)) and chunk_frames >= 1):
            raise ValueError(f"chunk_frames must be a positive int, got {chunk_frames!r}")
        for what, names in (("object", object_order), ("link", link_names), ("env body", env_names)):
            for n in names:
                check_name(what, n)
            if len(set(names)) != len(names):
                raise ValueError(f"duplicate {what} names in {list(names)}")
        if not object_order:
            raise ValueError("object_order is empty: a store needs at least one simulated object")
        self.chunk_frames = int(chunk_frames)
        self.object_order = list(object_order)
        self.link_names = list(link_names)
        self.env_names = list(env_names)
        self._root_attrs = {
            "schema": SCHEMA, "dt": float(dt), "substeps": int(substeps), "units": str(units),
            "created_by": str(created_by), "params_hash": str(params_hash),
            "object_order": self.object_order, "link_names": self.link_names, "env_names": self.env_names,
        }
        self._vertex_counts: dict[str, int] = {}
        self._prescribed: list[str] = []
        self._episodes: set[str] = set()
        self._next_index = 0
        self._tmp: Path | None = None
        self._root: zarr.Group | None = None

    # -- context management -------------------------------------------------------------
    def __enter__(self) -> TrajectoryWriter:
        self._check_target()
        remove_stale_temporaries(self.path)
        parent = self.path.parent
        tmp = parent / f"{self.path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}"
        try:
            parent.mkdir(parents=True, exist_ok=True)
            os.mkdir(tmp)
        except PermissionError as e:
            raise PermissionError(e.errno, f"cannot write trajectory store {self.path}: "
                                  f"directory {parent} is not writable ({e.strerror})") from e
        except OSError as e:
            raise OSError(e.errno, f"cannot write trajectory store {self.path}: "
                          f"cannot create {tmp} ({e.strerror})") from e
        self._tmp = tmp
        try:
            self._root = zarr.open_group(tmp, mode="w", zarr_format=3)
            self._root.attrs.update(self._root_attrs)
            for g in ("objects", "prescribed", "episodes"):
                self._root.create_group(g)
            if self.write_processes:
                self._pool = spawn_pool(self.write_processes)
                for _ in range(self.write_processes):  # each starts (imports zarr) now, not at the first episode
                    self._pool.submit(os.getpid)
        except BaseException:
            self._abort()
            raise
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is not None:
            self._abort()
            return
        try:
            self._commit()
        except BaseException:
            self._abort()
            raise

    def _check_target(self) -> None:
        """Refuse to replace anything but a trajectory store (or an empty directory) at `path`."""
        p = self.path
        if p.is_symlink() or (p.exists() and not p.is_dir()):
            raise FileExistsError(f"{p} exists and is not a directory; refusing to replace it")
        if p.is_dir() and any(p.iterdir()) and not (p / "zarr.json").is_file():
            raise FileExistsError(f"{p} is a non-empty directory that is not a zarr store; refusing to replace it")

    def _drain(self, cancel: bool = False) -> None:
        """Wait for the episodes the write processes hold (a failed write raises here; cancel: drop those not
        started) and stop the processes."""
        pool, pending, self._pool, self._pending = self._pool, self._pending, None, []
        if pool is None:
            return
        pool.shutdown(wait=True, cancel_futures=cancel)
        if not cancel:
            for f in pending:
                f.result()

    def _commit(self) -> None:
        assert self._tmp is not None and self._root is not None
        self._drain()
        missing = [n for n in self.object_order if n not in self._vertex_counts]
        if missing:
            raise ValueError(f"{self.path}: objects {missing} in object_order were never added (add_object)")
        self._root.attrs.update({"object_offsets": self._offsets(), "prescribed_order": self._prescribed})
        self._check_target()
        old = None
        if self.path.exists():
            old = self.path.with_name(f"{self.path.name}.tmp-old-{os.getpid()}-{secrets.token_hex(4)}")
            os.rename(self.path, old)
        try:
            os.rename(self._tmp, self.path)
        except BaseException:
            if old is not None:
                os.rename(old, self.path)
            raise
        self._tmp = self._root = None
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def _abort(self) -> None:
        self._drain(cancel=True)
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
        self._tmp = self._root = None

    def _group(self, name: str) -> zarr.Group:
        if self._root is None:
            raise RuntimeError("TrajectoryWriter is not open: use it as `with TrajectoryWriter(...) as w:`")
        return self._root[name]  # type: ignore[return-value]

    def _offsets(self) -> list[int]:
        return [0, *np.cumsum([self._vertex_counts[n] for n in self.object_order]).tolist()]

    # -- scene ------------------------------------------------------------------------------
    def add_object(self, name: str, rest_positions: np.ndarray, faces: np.ndarray, rest_uv: np.ndarray,
                   vertex_area: np.ndarray, kind: str, tag: int, material: Mapping[str, Any]) -> None:
        """Add a simulated object: rest_positions (N, 3) m, faces (F, 3) int, rest_uv (N, 2), vertex_area (N,) m^2."""
        objects = self._group("objects")
        where = f"object '{name}'"
        if name not in self.object_order:
            raise ValueError(f"{where} is not in object_order {self.object_order}")
        if name in self._vertex_counts:
            raise ValueError(f"{where} was already added")
        if kind not in KINDS:
            raise ValueError(f"{where}: kind {kind!r} not in {KINDS}")
        if not isinstance(tag, (int, np.integer)) or isinstance(tag, bool):
            raise TypeError(f"{where}: tag must be an int, got {tag!r}")
        if not isinstance(material, Mapping):
            raise TypeError(f"{where}: material must be a dict, got {type(material).__name__}")
        pos = as_array("rest_positions", rest_positions, np.float32, where)
        check_shape("rest_positions", pos, (None, 3), where)
        n = pos.shape[0]
        if n == 0:
            raise ValueError(f"{where}: rest_positions has no vertices")
        f = np.asarray(faces)
        if f.dtype.kind not in "iu":
            raise TypeError(f"{where}: array 'faces' has dtype {f.dtype}, expected an integer type")
        check_shape("faces", f, (None, 3), where)
        if f.size and (f.min() < 0 or f.max() >= n):
            raise ValueError(f"{where}: faces index vertices outside [0, {n}) (min {f.min()}, max {f.max()})")
        arrays = {
            "rest_positions": pos,
            "faces": f.astype(np.int32),
            "rest_uv": as_array("rest_uv", rest_uv, np.float32, where),
            "vertex_area": as_array("vertex_area", vertex_area, np.float32, where),
        }
        check_shape("rest_uv", arrays["rest_uv"], (n, 2), where)
        check_shape("vertex_area", arrays["vertex_area"], (n,), where)
        for k in ("rest_positions", "rest_uv", "vertex_area"):
            check_finite(k, arrays[k], where)
        g = objects.create_group(name)
        for k, a in arrays.items():
            write_array(g, k, a)
        g.attrs.update({"kind": kind, "tag": int(tag), "material": jsonable(dict(material), f"{where}.material")})
        self._vertex_counts[name] = n

    def add_prescribed(self, name: str, local_points: np.ndarray, local_normals: np.ndarray,
                       tag: int, link: str) -> None:
        """Add a prescribed sample set: local_points (M, 3) m and local_normals (M, 3) in the frame of `link`."""
        prescribed = self._group("prescribed")
        where = f"prescribed '{name}'"
        check_name("prescribed", name)
        if name in self._prescribed:
            raise ValueError(f"{where} was already added")
        if link not in self.link_names and link not in self.env_names:
            raise ValueError(f"{where}: link {link!r} is neither in link_names {self.link_names} "
                             f"nor in env_names {self.env_names}")
        if not isinstance(tag, (int, np.integer)) or isinstance(tag, bool):
            raise TypeError(f"{where}: tag must be an int, got {tag!r}")
        pts = as_array("local_points", local_points, np.float32, where)
        nrm = as_array("local_normals", local_normals, np.float32, where)
        check_shape("local_points", pts, (None, 3), where)
        check_shape("local_normals", nrm, (pts.shape[0], 3), where)
        check_finite("local_points", pts, where)
        check_finite("local_normals", nrm, where)
        g = prescribed.create_group(name)
        write_array(g, "local_points", pts)
        write_array(g, "local_normals", nrm)
        g.attrs.update({"tag": int(tag), "link": link})
        self._prescribed.append(name)

    def add_scene(self, scene: Scene, materials: Mapping[str, Mapping[str, Any]] | None = None) -> None:
        """Every object mesh (with its material, by object name) and prescribed sample set of a built scene."""
        for name, mesh in scene.objects.items():
            self.add_object(name, mesh.vertices, mesh.faces, mesh.rest_uv, mesh.vertex_area,
                            kind=scene.object_kinds[name], tag=mesh.tag, material=(materials or {}).get(name, {}))
        for samples in scene.samples:
            self.add_prescribed(samples.name, samples.local_points, samples.local_normals, samples.tag, samples.body)

    # -- episodes ---------------------------------------------------------------------------
    def add_episode(self, x: np.ndarray, v: np.ndarray, action: np.ndarray, link_poses: np.ndarray,
                    env_poses: np.ndarray, *, episode_id: str | None = None, **attrs: Any) -> str:
        """Validate and write one episode; returns its id (next ``ep_%06d`` unless `episode_id` is given).

        x, v (T, N_e, 3) m, m/s; action (T, 14); link_poses (T, L_e, 7); env_poses (T, E, 7), where the
        optional attrs `objects` / `links` choose the present objects and link columns (default: all).
        `attrs` must hold task, seed, cell, speed, amplitude, split, accepted, first_failure,
        source; extra JSON-serialisable attrs are kept.
        """
        episodes = self._group("episodes")
        missing = [n for n in self.object_order if n not in self._vertex_counts]
        if missing:
            raise RuntimeError(f"add_object({missing}) must be called before add_episode")
        eid = episode_id if episode_id is not None else format_episode_id(self._next_index)
        if not isinstance(eid, str) or not EPISODE_RE.match(eid):
            raise ValueError(f"episode id {eid!r} must look like 'ep_000000'")
        if eid in self._episodes:
            raise ValueError(f"episode {eid} was already written")
        where = f"episode {eid}"
        clean_attrs = self._check_attrs(attrs, where)
        objects = subsequence(clean_attrs.get("objects", self.object_order), self.object_order, "objects", where)
        links = subsequence(clean_attrs.get("links", self.link_names), self.link_names, "links", where)
        n_total = sum(self._vertex_counts[n] for n in objects)
        L, E = len(links), len(self.env_names)
        arrays = {k: as_array(k, a, np.float32, where)
                  for k, a in zip(EPISODE_ARRAYS, (x, v, action, link_poses, env_poses))}
        T = arrays["x"].shape[0] if arrays["x"].ndim else 0
        if T < 1:
            raise ValueError(f"{where}: episode needs at least one frame, x has shape {arrays['x'].shape}")
        shapes = {"x": (T, n_total, 3), "v": (T, n_total, 3), "action": (T, ACTION_DIM),
                  "link_poses": (T, L, POSE_DIM), "env_poses": (T, E, POSE_DIM)}
        for k, a in arrays.items():
            check_shape(k, a, shapes[k], where)
        for k, a in arrays.items():
            check_finite(k, a, where)
        if self._pool is None:
            write_episode(episodes, eid, arrays, clean_attrs, self.chunk_frames)
        else:  # checked here, written there: the arrays travel pickled
            while self._pending and self._pending[0].done():
                self._pending.pop(0).result()  # a failed write stops the writer at the next episode
            self._pending.append(self._pool.submit(_write_in_process, str(self._tmp), eid, arrays, clean_attrs,
                                                   self.chunk_frames))
        self._episodes.add(eid)
        self._next_index = max(self._next_index, int(eid[3:]) + 1)
        return eid

    @staticmethod
    def _check_attrs(attrs: Mapping[str, Any], where: str) -> dict[str, Any]:
        missing = [k for k in EPISODE_ATTRS if k not in attrs]
        if missing:
            raise ValueError(f"{where}: missing required attrs {missing}")
        out = {k: jsonable(v, f"{where} attr '{k}'") for k, v in attrs.items()}
        if out["split"] not in SPLITS:
            raise ValueError(f"{where}: split {out['split']!r} not in {SPLITS}")
        if out["source"] not in SOURCES:
            raise ValueError(f"{where}: source {out['source']!r} not in {SOURCES}")
        if not isinstance(out["accepted"], bool):
            raise TypeError(f"{where}: accepted must be a bool, got {out['accepted']!r}")
        if not isinstance(out["seed"], int) or isinstance(out["seed"], bool):
            raise TypeError(f"{where}: seed must be an int, got {out['seed']!r}")
        if not isinstance(out["task"], str) or not out["task"]:
            raise TypeError(f"{where}: task must be a non-empty str, got {out['task']!r}")
        return out


def write_episode(episodes: zarr.Group, eid: str, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any],
                  chunk_frames: int) -> None:
    """One checked episode's group under a store's `episodes` group."""
    g = episodes.create_group(eid)
    for k, a in arrays.items():
        write_array(g, k, a, chunk_frames)
    g.attrs.update(attrs)


_OPEN: dict[str, zarr.Group] = {}  # a write process's open `episodes` groups, by store folder


def _write_in_process(store: str, eid: str, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any],
                      chunk_frames: int) -> None:
    if store not in _OPEN:
        _OPEN[store] = zarr.open_group(store, mode="r+")["episodes"]
    write_episode(_OPEN[store], eid, arrays, attrs, chunk_frames)
