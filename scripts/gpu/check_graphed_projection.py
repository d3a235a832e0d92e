"""GPU check: the shipped model's static rollout with the topology projection, CUDA-graphed (the projection's kernels
captured inside the step's graph) against the same rollout without graphs, on a synthetic episode.

    python scripts/gpu/check_graphed_projection.py   -> prints the largest position difference; exit 1 on failure
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from pathlib import Path

import torch

from tests.synthetic_store import write_synthetic_store
from wc.config import load_section, read_params
from wc.data.store import TrajectoryStore
from wc.model.predictor import WorldContactPredictor
from wc.model.layout import scene_layout
from wc.train.config import TrainConfig
from wc.train.data import episode_phases, read_phase_window

MODEL = "models/pretrained/worldcontact-lift-handle"


def main() -> int:
    params = read_params("params.yaml")
    device = torch.device("cuda")
    with tempfile.TemporaryDirectory() as tmp:
        store = TrajectoryStore(write_synthetic_store(Path(tmp) / "s.zarr", params, [("carry", "test")], frames=12))
        phase = episode_phases(store, store.episode_ids[0])[0]
        a = {k: torch.from_numpy(v)[None].to(device) for k, v in read_phase_window(store, phase, 0, 11).items()}
        base = dataclasses.replace(load_section(params, "train", TrainConfig), static=True, autocast_bf16=False)
        out = {}
        for graphed in (False, True):
            predictor = WorldContactPredictor.from_dir(MODEL, dataclasses.replace(base, cuda_graph=graphed), device)
            layout = scene_layout(store, list(phase.layout[0]), list(phase.layout[1]), predictor.tag_scale).to(device)
            out[graphed] = predictor.rollout(layout, a["x"][:, 0], a["v"][:, 0], a["poses"], store.dt)[0]
    diff = float((out[True] - out[False]).abs().max())
    print(f"projection={predictor.projection}; graphed vs eager static rollout: max |dx| = {diff:.3e} m")
    return 0 if torch.isfinite(out[True]).all() and diff < 1e-4 else 1


if __name__ == "__main__":
    sys.exit(main())
