"""Trajectory store (Zarr v3): writer, read-only reader and subset copy.

Layout (see DESIGN.md, "Trajectory store"); all float arrays float32, faces int32:

    <store>.zarr/
      attrs: schema, dt (s), substeps, units, created_by, params_hash,
             object_order    [name, ...]      objects in the order x concatenates them
             object_offsets  [0, N_0, ...]    vertex offsets, len(object_order) + 1
             prescribed_order [name, ...]     prescribed sample sets, in insertion order
             link_names      [name, ...]      columns of link_poses (L)
             env_names       [name, ...]      columns of env_poses (E)
      objects/<name>/     rest_positions (N, 3) m, faces (F, 3), rest_uv (N, 2), vertex_area (N,) m^2
                          attrs: kind (cloth|rigid), tag (int), material (dict)
      prescribed/<name>/  local_points (M, 3) m, local_normals (M, 3); attrs: tag (int), link (str)
      episodes/ep_000000/ x, v (T, N_e, 3) m, m/s; action (T, 14);
                          link_poses (T, L_e, 7), env_poses (T, E, 7): pos m, quat xyzw
                          attrs: task, seed, cell, speed, amplitude, split, accepted,
                                 first_failure, source (+ any extra JSON attrs)
                          optional layout attrs (default: everything in the store):
                            objects  [name, ...]  the objects present, in object_order; x concatenates
                                                  them (N_e = their vertex count)
                            links    [name, ...]  columns of link_poses (L_e), a subsequence of link_names
                            held     {object: {link, local_pose}}  held (prescribed) objects and where
                            handoff  {object: k}  the object is prescribed (pose `held_<object>`) in
                                                  frames < k and predicted from frame k on; its rows of x
                                                  follow the held pose before k

Episode arrays are chunked along T only (`chunk_frames` frames per chunk) and zstd compressed,
so a short window reads one or two chunks. Float arrays have fill value NaN: a missing chunk
reads as NaN and the reader reports the store as corrupt instead of returning zeros.
"""

from __future__ import annotations

import math
import os
import re
import secrets
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
import zarr
from zarr.codecs import ZstdCodec

from wc.atomic import remove_stale_temporaries

if TYPE_CHECKING:
    from wc.scene.scene import Scene

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
_EPISODE_RE = re.compile(r"^ep_\d{6,}$")
_ZSTD = ZstdCodec(level=3)


def format_episode_id(index: int) -> str:
    """Episode id for an index: ``ep_000042`` (sorts lexicographically up to 10^6 episodes)."""
    return f"ep_{index:06d}"


def _episode_sort_key(eid: str) -> tuple[int, str]:
    return (len(eid), eid)


def _check_name(what: str, name: str) -> None:
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ValueError(f"invalid {what} name {name!r}: use letters, digits, '_', '.', '-'")


def _jsonable(value: Any, where: str) -> Any:
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
            out[k] = _jsonable(v, f"{where}.{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{where}: non-finite value {value!r} is not allowed in attrs")
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise ValueError(f"{where}: value {value!r} of type {type(value).__name__} is not JSON-serialisable")


def _as_array(name: str, a: Any, dtype: type, where: str) -> np.ndarray:
    """`a` as a C-contiguous array of `dtype`, refusing lossy kinds (e.g. float -> int, str -> float)."""
    arr = np.asarray(a)
    if not np.can_cast(arr.dtype, dtype, casting="same_kind"):
        raise TypeError(f"{where}: array '{name}' has dtype {arr.dtype}, not castable to {np.dtype(dtype)}")
    return np.ascontiguousarray(arr, dtype=dtype)


def _check_shape(name: str, arr: np.ndarray, shape: tuple[int | None, ...], where: str) -> None:
    ok = arr.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, arr.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{where}: array '{name}' has shape {arr.shape}, expected {want}")


def _subsequence(names: Any, full: Sequence[str], what: str, where: str) -> list[str]:
    """`names` as a list, checked to be a non-repeating subsequence of `full` in its order."""
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise TypeError(f"{where}: attr '{what}' must be a list of names, got {names!r}")
    unknown = [n for n in names if n not in full]
    if unknown:
        raise ValueError(f"{where}: attr '{what}' names {unknown}, not in the store's {list(full)}")
    if list(names) != [n for n in full if n in names]:
        raise ValueError(f"{where}: attr '{what}' {list(names)} must follow the store's order {list(full)}")
    return list(names)


def _check_finite(name: str, arr: np.ndarray, where: str) -> None:
    """Raise if `arr` has NaN/Inf, naming the first bad index along axis 0 (the frame for episodes)."""
    if arr.size and not np.isfinite(arr).all():
        bad = int(np.argmax(~np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1)))
        raise ValueError(f"{where}: array '{name}' has non-finite values (NaN/Inf), first at index {bad}")


def _chunks(shape: tuple[int, ...], first: int | None = None) -> tuple[int, ...]:
    c = [max(1, d) for d in shape]
    if first is not None:
        c[0] = max(1, min(first, shape[0]))
    return tuple(c)


def _write_array(group: zarr.Group, name: str, arr: np.ndarray, chunk_frames: int | None = None) -> None:
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


class TrajectoryWriter:
    """Write a trajectory store episode by episode; atomic on success, nothing left on failure.

    Use as ``with TrajectoryWriter(path, ...) as w:``. Data goes to ``<path>.tmp-<pid>-<hex>``
    and is renamed to `path` on a clean exit (an existing store at `path` is replaced); on an
    exception the temporary directory is removed (one a killed writer left is removed when the next one
    starts: wc.atomic). Call `add_object` for every name in
    `object_order` before the first `add_episode`.
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
    ) -> None:
        self.path = Path(path)
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a positive finite number of seconds, got {dt!r}")
        if not (isinstance(substeps, (int, np.integer)) and substeps >= 1):
            raise ValueError(f"substeps must be a positive int, got {substeps!r}")
        if not (isinstance(chunk_frames, (int, np.integer)) and chunk_frames >= 1):
            raise ValueError(f"chunk_frames must be a positive int, got {chunk_frames!r}")
        for what, names in (("object", object_order), ("link", link_names), ("env body", env_names)):
            for n in names:
                _check_name(what, n)
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

    def _commit(self) -> None:
        assert self._tmp is not None and self._root is not None
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
        pos = _as_array("rest_positions", rest_positions, np.float32, where)
        _check_shape("rest_positions", pos, (None, 3), where)
        n = pos.shape[0]
        if n == 0:
            raise ValueError(f"{where}: rest_positions has no vertices")
        f = np.asarray(faces)
        if f.dtype.kind not in "iu":
            raise TypeError(f"{where}: array 'faces' has dtype {f.dtype}, expected an integer type")
        _check_shape("faces", f, (None, 3), where)
        if f.size and (f.min() < 0 or f.max() >= n):
            raise ValueError(f"{where}: faces index vertices outside [0, {n}) (min {f.min()}, max {f.max()})")
        arrays = {
            "rest_positions": pos,
            "faces": f.astype(np.int32),
            "rest_uv": _as_array("rest_uv", rest_uv, np.float32, where),
            "vertex_area": _as_array("vertex_area", vertex_area, np.float32, where),
        }
        _check_shape("rest_uv", arrays["rest_uv"], (n, 2), where)
        _check_shape("vertex_area", arrays["vertex_area"], (n,), where)
        for k in ("rest_positions", "rest_uv", "vertex_area"):
            _check_finite(k, arrays[k], where)
        g = objects.create_group(name)
        for k, a in arrays.items():
            _write_array(g, k, a)
        g.attrs.update({"kind": kind, "tag": int(tag), "material": _jsonable(dict(material), f"{where}.material")})
        self._vertex_counts[name] = n

    def add_prescribed(self, name: str, local_points: np.ndarray, local_normals: np.ndarray,
                       tag: int, link: str) -> None:
        """Add a prescribed sample set: local_points (M, 3) m and local_normals (M, 3) in the frame of `link`."""
        prescribed = self._group("prescribed")
        where = f"prescribed '{name}'"
        _check_name("prescribed", name)
        if name in self._prescribed:
            raise ValueError(f"{where} was already added")
        if link not in self.link_names and link not in self.env_names:
            raise ValueError(f"{where}: link {link!r} is neither in link_names {self.link_names} "
                             f"nor in env_names {self.env_names}")
        if not isinstance(tag, (int, np.integer)) or isinstance(tag, bool):
            raise TypeError(f"{where}: tag must be an int, got {tag!r}")
        pts = _as_array("local_points", local_points, np.float32, where)
        nrm = _as_array("local_normals", local_normals, np.float32, where)
        _check_shape("local_points", pts, (None, 3), where)
        _check_shape("local_normals", nrm, (pts.shape[0], 3), where)
        _check_finite("local_points", pts, where)
        _check_finite("local_normals", nrm, where)
        g = prescribed.create_group(name)
        _write_array(g, "local_points", pts)
        _write_array(g, "local_normals", nrm)
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
        if not isinstance(eid, str) or not _EPISODE_RE.match(eid):
            raise ValueError(f"episode id {eid!r} must look like 'ep_000000'")
        if eid in self._episodes:
            raise ValueError(f"episode {eid} was already written")
        where = f"episode {eid}"
        clean_attrs = self._check_attrs(attrs, where)
        objects = _subsequence(clean_attrs.get("objects", self.object_order), self.object_order, "objects", where)
        links = _subsequence(clean_attrs.get("links", self.link_names), self.link_names, "links", where)
        n_total = sum(self._vertex_counts[n] for n in objects)
        L, E = len(links), len(self.env_names)
        arrays = {k: _as_array(k, a, np.float32, where)
                  for k, a in zip(EPISODE_ARRAYS, (x, v, action, link_poses, env_poses))}
        T = arrays["x"].shape[0] if arrays["x"].ndim else 0
        if T < 1:
            raise ValueError(f"{where}: episode needs at least one frame, x has shape {arrays['x'].shape}")
        shapes = {"x": (T, n_total, 3), "v": (T, n_total, 3), "action": (T, ACTION_DIM),
                  "link_poses": (T, L, POSE_DIM), "env_poses": (T, E, POSE_DIM)}
        for k, a in arrays.items():
            _check_shape(k, a, shapes[k], where)
        for k, a in arrays.items():
            _check_finite(k, a, where)
        g = episodes.create_group(eid)
        for k, a in arrays.items():
            _write_array(g, k, a, self.chunk_frames)
        g.attrs.update(clean_attrs)
        self._episodes.add(eid)
        self._next_index = max(self._next_index, int(eid[3:]) + 1)
        return eid

    @staticmethod
    def _check_attrs(attrs: Mapping[str, Any], where: str) -> dict[str, Any]:
        missing = [k for k in EPISODE_ATTRS if k not in attrs]
        if missing:
            raise ValueError(f"{where}: missing required attrs {missing}")
        out = {k: _jsonable(v, f"{where} attr '{k}'") for k, v in attrs.items()}
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
            self._episode_ids = sorted(keys, key=_episode_sort_key)
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
            a = np.asarray(arrs[k][sl])
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


def copy_store(
    src: TrajectoryStore,
    dst_path: str | os.PathLike[str],
    episode_ids: Sequence[str],
    attr_updates: Mapping[str, Mapping[str, Any]] | None = None,
    *,
    created_by: str | None = None,
    params_hash: str | None = None,
    chunk_frames: int | None = None,
) -> TrajectoryStore:
    """Write a new store at `dst_path` with `src`'s scene and the given episodes (ids kept), attrs updated.

    `attr_updates[eid]` is merged into that episode's attrs (e.g. ``{"split": "val"}``). Episodes
    are copied one at a time. `created_by`, `params_hash`, `chunk_frames` default to the source's.
    """
    attr_updates = dict(attr_updates or {})
    ids = list(episode_ids)
    known = set(src.episode_ids)
    unknown = [e for e in ids if e not in known]
    if unknown:
        raise KeyError(f"{src.path}: episodes {unknown} not in store")
    if len(set(ids)) != len(ids):
        raise ValueError("episode_ids has duplicates")
    stray = [e for e in attr_updates if e not in set(ids)]
    if stray:
        raise ValueError(f"attr_updates names episodes not being copied: {stray}")
    a = src.attrs
    if chunk_frames is None:
        chunk_frames = src.chunk_frames(ids[0]) if ids else 16
    with TrajectoryWriter(
        dst_path, dt=a["dt"], substeps=a["substeps"], units=a["units"],
        created_by=a["created_by"] if created_by is None else created_by,
        params_hash=a["params_hash"] if params_hash is None else params_hash,
        object_order=src.object_names, link_names=src.link_names, env_names=src.env_names,
        chunk_frames=chunk_frames,
    ) as w:
        for o in src.objects.values():
            w.add_object(o.name, o.rest_positions, o.faces, o.rest_uv, o.vertex_area, o.kind, o.tag, o.material)
        for p in src.prescribed.values():
            w.add_prescribed(p.name, p.local_points, p.local_normals, p.tag, p.link)
        for eid in ids:
            attrs = {**src.episode_attrs(eid), **attr_updates.get(eid, {})}
            w.add_episode(**src.read_episode(eid), episode_id=eid, **attrs)
    return TrajectoryStore(dst_path)
