"""Small trajectory stores with simple, learnable motion on the real scene meshes and sample sets.

Used by the model, training and stage tests (the Newton-made store is a DVC artefact, not in git).
Episode kinds:
  fall     the bag drops from a few cm under gravity and stops on the table;
  carry    the bag slides along +x at constant speed with the right arm's links moving alongside;
  handoff  a held sphere rides on the right gripper, then (from its release frame) falls beside the bag.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from wc.config import load_section
from wc.data.store import TrajectoryWriter
from wc.scene.config import SceneConfig
from wc.scene.scene import build_scene

DT = 0.04
GRAVITY = 9.81
HELD_SPHERE = {"sphere": ("right_link6", [0.0, 0.0, 0.16, 0.0, 0.0, 0.0, 1.0])}


def _fall(z0: np.ndarray, drop: float, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Heights and vertical velocities of points dropped by `drop` m that stop on landing."""
    t = np.arange(frames)[:, None] * DT
    fallen = np.minimum(0.5 * GRAVITY * t ** 2, drop)
    vz = np.where(0.5 * GRAVITY * t ** 2 < drop, -GRAVITY * t, 0.0)
    return z0[None] + drop - fallen, np.broadcast_to(vz, (frames, z0.shape[0]))


def _episode(scene_cfg: SceneConfig, kind: str, frames: int, rng: np.random.Generator) -> tuple[dict, dict]:
    held = {"sphere": HELD_SPHERE["sphere"]} if kind == "handoff" else {}
    objects = ["bag", "sphere"] if kind == "handoff" else ["bag"]
    scene = build_scene(scene_cfg, objects, held=held)
    bag = scene.objects["bag"].vertices.astype(np.float64) + np.r_[rng.uniform(-0.02, 0.02, 2), 0.0]
    action = np.repeat(scene.home_action()[None], frames, axis=0)
    x = np.repeat(bag[None], frames, axis=0)
    v = np.zeros_like(x)
    attrs: dict[str, Any] = {"objects": objects, "links": list(scene.link_names)}
    if kind == "fall":
        x[..., 2], v[..., 2] = _fall(bag[:, 2], rng.uniform(0.02, 0.04), frames)
    elif kind == "carry":
        speed = rng.uniform(0.05, 0.1)
        shift = np.arange(frames)[:, None] * DT * speed
        x[..., 0] += shift
        v[..., 0] = speed
        action[:, 7] += np.arange(frames) * DT * speed * 2.0  # right base yaw turns: the arm sweeps along
    link_poses = scene.link_poses(action)
    if kind == "handoff":
        release = frames // 2
        ball = scene.objects["sphere"].vertices.astype(np.float64)
        centre = link_poses[release, list(scene.link_names).index("held_sphere"), :3]
        rows = np.repeat((ball - ball.mean(0) + centre)[None], frames, axis=0)
        height = centre[2] - scene_cfg.sphere.radius_m
        z, vz = _fall(rows[release, :, 2] - height, height, frames - release)
        rows[release:, :, 2], sphere_v = z, np.zeros((frames, ball.shape[0], 3))
        sphere_v[release:, :, 2] = vz
        x, v = np.concatenate([x, rows], axis=1), np.concatenate([v, sphere_v], axis=1)
        attrs.update(held={"sphere": {"link": HELD_SPHERE["sphere"][0], "local_pose": HELD_SPHERE["sphere"][1]}},
                     handoff={"sphere": release})
    arrays = dict(x=x, v=v, action=action, link_poses=link_poses,
                  env_poses=np.repeat(scene.env_poses()[None], frames, axis=0))
    return arrays, attrs


def write_synthetic_store(path: Path, params: dict[str, Any], episodes: list[tuple[str, str]],
                          frames: int = 12, seed: int = 0) -> Path:
    """A store at `path` with one episode per (kind, split) entry, on `params`' scene."""
    scene_cfg = load_section(params, "scene", SceneConfig)
    full = build_scene(scene_cfg, ["bag", "sphere", "cube"], held=HELD_SPHERE)
    rng = np.random.default_rng(seed)
    with TrajectoryWriter(path, dt=DT, substeps=20, params_hash="synthetic", created_by="tests",
                          object_order=list(full.objects), link_names=list(full.link_names),
                          env_names=list(full.env_names), chunk_frames=8) as w:
        w.add_scene(full)
        for i, (kind, split) in enumerate(episodes):
            arrays, layout = _episode(scene_cfg, kind, frames, rng)
            w.add_episode(**arrays, episode_id=f"ep_{i:06d}", task=kind, seed=i, cell=0, speed=0.1, amplitude=0.0,
                          split=split, accepted=True, first_failure=None, source="simulator", **layout)
    return path
