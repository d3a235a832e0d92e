"""The expand stage on the slot engine (`expand.engine: slots`): the world model, its layout, the fixed projection and
the checks built for the stage's scene, the slots run by wc.expand.slot_expansion, and each filed episode written to
the generated stores."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from wc.config import load_section
from wc.data.store import TrajectoryStore, TrajectoryWriter
from wc.devices import resolve_device
from wc.expand.config import ExpandConfig
from wc.expand.fixed_projection import FixedProjectionConfig, FixedStepProjection
from wc.expand.frame_checks import FrameChecks
from wc.expand.generated_store import episode_attrs
from wc.expand.plan import SourceEpisode
from wc.expand.plan_pool import PlanPool
from wc.expand.slot_expansion import SlotExpansion
from wc.expand.slot_rollout import SlotRollout
from wc.model.layout import scene_layout
from wc.model.predictor import WorldContactPredictor
from wc.model.prescribed_inputs import KinematicInputs
from wc.scene.scene import Scene
from wc.sim.config import SimConfig
from wc.tasks.base import Task
from wc.train.capacity import initial_capacities
from wc.train.config import TrainConfig
from wc.validate.config import ValidateConfig


def fixed_projection_config(cfg: ExpandConfig, sim: SimConfig) -> FixedProjectionConfig:
    """The slot engine's projection from the expand params (projection_edge_ratio, self_contact, untangle, the
    `slots` pass counts) and the simulator's self-contact gap and filter rings."""
    s = cfg.slots
    return FixedProjectionConfig(
        edge_ratio=tuple(cfg.projection_edge_ratio), iterations=s.iterations, final_edge_passes=s.final_edge_passes,
        self_contact_gap_m=sim.self_contact_gap_m if cfg.self_contact else None,
        self_contact_rings=sim.self_contact_filter_rings, untangle_share=cfg.untangle_share,
        bounded_rounds=s.bounded_rounds if "bounded" in cfg.untangle else 0, bounded_passes=s.bounded_passes,
        rollback_rounds=s.rollback_rounds if "rollback" in cfg.untangle else 0, rollback_full_from=cfg.untangle_rounds,
        vertex_pairs=s.vertex_pairs, edge_pairs=s.edge_pairs, pair_capacity=s.pair_capacity,
        self_contact_capacity=s.self_contact_capacity)


class SlotModel:
    """What every slot rollout of a run shares: the model on its device, the layout, the fixed projection, the
    checks and the neighbour capacities (the checkpoint's, else measured on the first source's first frames)."""

    def __init__(self, params: dict[str, Any], model_dir: Path, scene: Scene, src: TrajectoryStore,
                 sources: list[SourceEpisode], cfg: ExpandConfig, validate_cfg: ValidateConfig) -> None:
        self.cfg, self.validate_cfg, self.dt = cfg, validate_cfg, src.dt
        self.device = resolve_device(cfg.device, "expand.device")
        torch.manual_seed(cfg.seed)
        self.predictor = WorldContactPredictor.from_dir(model_dir, load_section(params, "train", TrainConfig),
                                                        self.device)
        self.layout = scene_layout(src, list(scene.objects), list(scene.link_names),
                                   self.predictor.tag_scale).to(self.device)
        self.link_columns = [self.layout.bodies.index(n) for n in scene.link_names]
        self.fixed = FixedStepProjection(scene, fixed_projection_config(cfg, load_section(params, "sim", SimConfig)),
                                         self.device)
        if cfg.slots.compile_projection and self.device.type == "cuda":
            self.fixed.compile_passes()
        self.checks = FrameChecks(scene, validate_cfg, self.fixed.bodies, self.device)
        self.steps: dict[tuple[int, str], Any] = {}  # network steps per (slot count, capacities): compiled once
        self.capacities = self.predictor.capacities
        if self.capacities is None:
            first = src.read_window(sources[0].eid, 0, 2, ("action",))["action"]
            poses = torch.as_tensor(KinematicInputs(scene).poses(first[None]), dtype=torch.float32, device=self.device)
            x0 = torch.as_tensor(sources[0].x0[None], dtype=torch.float32, device=self.device)
            self.capacities = initial_capacities(self.predictor.model.config, self.layout, x0, poses, self.dt)

    def rollout(self, frames: int, batch: int | None = None) -> SlotRollout:
        """`batch` slots (None: expand.batch_size) for episodes of up to `frames` frames."""
        return SlotRollout(self.predictor.model, self.layout, self.predictor.topology_projection(self.layout),
                           self.capacities, self.fixed, self.checks, self.link_columns, self.dt,
                           batch or self.cfg.batch_size,
                           frames, self.validate_cfg.self_intersection_every, bf16=self.cfg.slots.bf16,
                           cuda_graph=self.cfg.slots.cuda_graph, compile_network=self.cfg.slots.compile_network,
                           steps=self.steps)


def run_slots(model: SlotModel, pool: PlanPool, task: Task, scene: Scene, sources: list[SourceEpisode], wanted: int,
              writer: TrajectoryWriter | None, rejected_writer: TrajectoryWriter | None, started: float,
              model_sha256: str | None = None, shard: int = 0) -> SlotExpansion:
    """Expand on the slots, planning in `pool`, until the target is met or the attempts run out; each filed episode
    goes to `writer` (accepted) or `rejected_writer` (None: not kept); `shard`: whose plan seeds. Returns the finished
    expansion (its counts and timing)."""
    cfg, links = model.cfg, len(scene.link_names)
    bar = tqdm(total=wanted, desc=f"expand {task.name}", unit="trajectory")

    def write(accepted: bool, running: Any, x: np.ndarray, v: np.ndarray, failure: tuple[str, int] | None) -> None:
        target = writer if accepted else rejected_writer
        if target is None:
            return
        n = len(x)
        links_poses, env_poses = np.split(running.poses[:n], [links], axis=1)
        target.add_episode(x, v, running.planned.actions[:n], np.ascontiguousarray(links_poses),
                           np.ascontiguousarray(env_poses),
                           **episode_attrs(running.planned, running.source, failure[0] if failure else None,
                                           model_sha256))

    def filed(expansion: SlotExpansion) -> None:
        bar.n = expansion.accepted
        bar.set_postfix(generated=expansion.generated, rejected=expansion.generated - expansion.accepted)

    expansion = SlotExpansion(task, scene, sources, cfg, model.validate_cfg, model.dt, wanted, model.rollout, pool,
                              started, write, filed, shard)
    try:
        expansion.run()
    finally:
        bar.close()
    return expansion
