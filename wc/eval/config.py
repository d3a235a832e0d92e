"""The `evaluate` params section: rollout horizons, penetration thresholds, divergence bounds, methods."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

MethodKind = Literal["worldcontact", "baseline", "zero_motion", "constant_velocity"]
CHECKPOINT_KINDS = ("worldcontact", "baseline")


@dataclass(frozen=True)
class MethodSpec:
    """One evaluated method: a WorldContact checkpoint dir (model.safetensors + model.json), a baseline dir
    (wc.baselines.load_baseline), or a reference that needs no files."""

    kind: MethodKind
    path: str = ""  # checkpoint directory, relative to the working directory; absent -> skipped with a note

    def validate(self) -> None:
        if self.kind in CHECKPOINT_KINDS and not self.path:
            raise ValueError(f"kind {self.kind!r} needs a path (its checkpoint directory)")
        if self.kind not in CHECKPOINT_KINDS and self.path:
            raise ValueError(f"kind {self.kind!r} takes no path, got {self.path!r}")


@dataclass(frozen=True)
class EvaluateConfig:
    """Held-out rollouts (Table 1 analogue) and long stability rollouts of every method."""

    rollout_frames: int  # steps of each held-out rollout from its first frame (capped by the data)
    stability_frames: int  # steps of each long rollout (>= 100 = 4 s at paper settings; capped by the episode)
    methods: dict[str, MethodSpec]
    stability_per_task: int = 1  # long rollouts per task, from its longest episodes
    penetration_depth_m: float = 0.01  # cloth deeper than this inside table / robot / rigid objects penetrates
    contact_band_m: float = 0.01  # contact area: cloth within this signed distance of any geometry
    divergence_strain: float = 2.0  # a rollout diverges at the first step with max |len/rest - 1| above this ...
    divergence_penetration_pct: float = 25.0  # ... or more than this % of cloth area penetrating, or non-finite
    device: str = "cpu"  # cpu | cuda | cuda:k | auto
    seed: int = 0

    def validate(self) -> None:
        for name in ("rollout_frames", "stability_frames", "stability_per_task"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("penetration_depth_m", "contact_band_m", "divergence_strain", "divergence_penetration_pct"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.methods:
            raise ValueError("methods is empty: name at least one method to evaluate")
        if not (self.device in ("cpu", "cuda", "auto") or self.device.startswith("cuda:")):
            raise ValueError(f"device must be cpu, cuda, cuda:k or auto, got {self.device!r}")
