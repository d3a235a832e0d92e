"""The small inputs of the expand tests (tests/test_expand.py, tests/test_ray_stages.py): params with checks loose
enough for a tiny untrained model, two lift_handle source episodes and that model."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import torch

from tests.conftest import load_params
from tests.synthetic_store import write_synthetic_store
from wc.config import load_section
from wc.data.store import TrajectoryStore, copy_store
from wc.model.config import ModelConfig
from wc.model.worldcontact import WorldContact
from wc.train.checkpoint import save_weights

TASK = "lift_handle"
# Tolerances so loose that a tiny untrained model's rollouts pass every check (the acceptance path);
# the rejection test tightens one of them.
LOOSE = dict(max_speed_m_s=1e3, max_edge_strain=1e3, penetration_tol_m=10.0, self_intersection_every=10_000,
             release_opening_m=10.0, adhesion_radius_m=0.01, adhesion_window_s=0.4, adhesion_rise_m=0.03,
             workspace_min_m=[-10.0, -10.0, -10.0], workspace_max_m=[10.0, 10.0, 10.0],
             min_visible_fraction=1e-9, view_camera="top", val_per_task=0, test_per_task=0, split_seed=0)


def expand_params() -> dict[str, Any]:
    """params.yaml with loose checks, short lift_handle programs (~20 frames) and a small expansion."""
    p = load_params()
    p["validate"] = copy.deepcopy(LOOSE)
    p["tasks"][TASK].update(speed_range_m_s=[0.4, 0.5], amplitude_range_m=[0.02, 0.03], hold_s=0.0)  # ~20 frames
    p["tasks"]["common"].update(close_s=0.08)
    p["expand"].update(task=TASK, target_trajectories=4, max_attempts=6, batch_size=2, task_check=False, device="cpu",
                       seed=3)
    return p


def write_source_store(folder: Path, params: dict[str, Any]) -> Path:
    """Two lift_handle source episodes (the synthetic bag at rest, robot at home) and one of another task."""
    raw = write_synthetic_store(folder / "raw.zarr", params, [("fall", "train"), ("carry", "train"), ("fall", "test")],
                                frames=3)
    src = TrajectoryStore(raw)
    relabel = {"task": TASK, "cell": 1}
    return copy_store(src, folder / "s.zarr", src.episode_ids, {"ep_000000": relabel, "ep_000002": relabel}).path


def write_tiny_model(folder: Path, params: dict[str, Any]) -> Path:
    """An untrained one-level WorldContact with visible predictions, saved in `folder`/worldcontact."""
    torch.manual_seed(0)
    cfg = load_section({**params, "model": {**params["model"], "encoder_levels": 1, "decoder_layers": 1}},
                       "model", ModelConfig)
    model = WorldContact(cfg, velocity_m_s=0.3, delta_x_m=0.002, delta_v_m_s=0.05).eval()
    torch.nn.init.normal_(model.head.mlp[-1].weight, std=0.1)  # visible predictions
    d = folder / "worldcontact"
    d.mkdir()
    save_weights(model, d / "model.safetensors", {"projection": True, "dt": 0.04})
    return d
