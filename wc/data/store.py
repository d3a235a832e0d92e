"""Trajectory store (Zarr v3): the public API (schema in wc/data/schema.py, TrajectoryWriter in wc/data/writer.py,
TrajectoryStore in wc/data/reader.py), the subset copy and the concatenation of stores of one scene.

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

import os
from collections.abc import Mapping, Sequence
from typing import Any

from wc.data.reader import TrajectoryStore
from wc.data.schema import (ACTION_DIM, EPISODE_ARRAYS, EPISODE_ATTRS, KINDS, LAYOUT_ATTRS, POSE_DIM, ROOT_ATTRS, SCHEMA,
                            SCHEMA_PREFIX, SOURCES, SPLITS, ObjectMesh, PrescribedSamples, format_episode_id)
from wc.data.writer import TrajectoryWriter

__all__ = ["ACTION_DIM", "EPISODE_ARRAYS", "EPISODE_ATTRS", "KINDS", "LAYOUT_ATTRS", "POSE_DIM", "ROOT_ATTRS", "SCHEMA",
           "SCHEMA_PREFIX", "SOURCES", "SPLITS", "ObjectMesh", "PrescribedSamples", "TrajectoryStore",
           "TrajectoryWriter", "concatenate_stores", "copy_scene", "copy_store", "format_episode_id"]


def copy_scene(src: TrajectoryStore, writer: TrajectoryWriter) -> None:
    """The objects and prescribed sample sets of `src` into `writer`."""
    for o in src.objects.values():
        writer.add_object(o.name, o.rest_positions, o.faces, o.rest_uv, o.vertex_area, o.kind, o.tag, o.material)
    for p in src.prescribed.values():
        writer.add_prescribed(p.name, p.local_points, p.local_normals, p.tag, p.link)


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
        copy_scene(src, w)
        for eid in ids:
            attrs = {**src.episode_attrs(eid), **attr_updates.get(eid, {})}
            w.add_episode(**src.read_episode(eid), episode_id=eid, **attrs)
    return TrajectoryStore(dst_path)


def concatenate_stores(parts: Sequence[str | os.PathLike[str]], dst_path: str | os.PathLike[str]) -> TrajectoryStore:
    """Write at `dst_path` (atomically) the episodes of the stores `parts`, in order and numbered afresh, with the
    scene and root attrs of the first; every part must have the same root attrs (one scene, one params hash)."""
    if not parts:
        raise ValueError("concatenate_stores needs at least one store")
    stores = [TrajectoryStore(p) for p in parts]
    first = stores[0]
    for s in stores[1:]:
        if s.attrs != first.attrs:
            raise ValueError(f"{s.path}: its root attrs differ from {first.path}'s: stores of one scene and params "
                             "only can be concatenated")
    a = first.attrs
    with_episodes = [s for s in stores if s.episode_ids]
    chunk_frames = with_episodes[0].chunk_frames(with_episodes[0].episode_ids[0]) if with_episodes else 16
    with TrajectoryWriter(dst_path, dt=a["dt"], substeps=a["substeps"], units=a["units"], created_by=a["created_by"],
                          params_hash=a["params_hash"], object_order=first.object_names, link_names=first.link_names,
                          env_names=first.env_names, chunk_frames=chunk_frames) as w:
        copy_scene(first, w)
        for s in stores:
            for eid in s.episode_ids:
                w.add_episode(**s.read_episode(eid), **s.episode_attrs(eid))
    return TrajectoryStore(dst_path)
