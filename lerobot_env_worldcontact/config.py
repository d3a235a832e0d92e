"""`WorldContactEnvConfig`: lerobot's EnvConfig for the lift task (choice name `worldcontact`).

Observation keys follow lerobot's convention for dict-of-cameras envs: `pixels/<camera>` (the env's
obs["pixels"][<camera>]) -> observation.images.<camera>, `agent_pos` -> observation.state. The image
size is read from the params file's `render` section, the one the dataset stage rendered at.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from wc.config import load_section, read_params
from wc.render.config import RenderConfig

ENV_TYPE = "worldcontact"
TASK = "LiftBag-v0"
GYM_ID = f"gym_{ENV_TYPE}/{TASK}"  # EnvConfig.gym_id: <package_name>/<task>
STATE_DIM = 7  # right arm q_R (6, rad) + gripper opening d_R (m)


@EnvConfig.register_subclass(ENV_TYPE)
@dataclass
class WorldContactEnvConfig(EnvConfig):
    task: str | None = TASK
    fps: int = 25  # 1 / frame dt (sim.dt_s * sim.substeps)
    params: str = "params.yaml"  # sections policy_eval, policy, scene, sim, render, tasks
    overrides: list[str] = field(default_factory=list)  # key.sub=value, e.g. policy_eval.hold_s=1.0
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.task != TASK:
            raise ValueError(f"env.task must be {TASK!r}, got {self.task!r}")
        render = load_section(read_params(Path(self.params), list(self.overrides)), "render", RenderConfig)
        image = PolicyFeature(type=FeatureType.VISUAL, shape=(render.height, render.width, 3))
        self.features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(STATE_DIM,)),
                         "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
                         **{f"pixels/{cam}": image for cam in render.cameras}}
        self.features_map = {ACTION: ACTION, "agent_pos": OBS_STATE,
                             **{f"pixels/{cam}": f"{OBS_IMAGES}.{cam}" for cam in render.cameras}}

    @property
    def gym_kwargs(self) -> dict:
        return {"params": self.params, "overrides": list(self.overrides)}
