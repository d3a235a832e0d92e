"""The `evaluate` params section: rollout horizons, penetration thresholds, divergence bounds, methods."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from wc.devices import check_device_name

MethodKind = Literal["worldcontact", "baseline", "zero_motion", "constant_velocity", "newton"]
CHECKPOINT_KINDS = ("worldcontact", "baseline")
NEWTON_KEYS = ("iterations", "substeps", "cloth_vertices_scale")  # settings only kind newton takes
WORLDCONTACT_KEYS = ("autocast_bf16", "cuda_graph")  # settings only kind worldcontact takes


@dataclass(frozen=True)
class MethodSpec:
    """One evaluated method: a WorldContact checkpoint dir (model.safetensors + model.json), a baseline dir
    (wc.baselines.load_baseline), a reference that needs no files, or the Newton source simulator at params
    `sim` with the overrides below (unset: as in params `sim` / `scene`)."""

    kind: MethodKind
    path: str = ""  # checkpoint directory, relative to the working directory; absent -> skipped with a note
    iterations: int | None = None  # newton: VBD iterations per solver step
    substeps: int | None = None  # newton: solver steps per frame; the solver dt becomes frame dt / substeps
    cloth_vertices_scale: float | None = None  # newton: every cloth mesh built at this x its target_vertices
    autocast_bf16: bool | None = None  # worldcontact: roll out under bf16 autocast (CUDA) or not; unset: params train
    cuda_graph: bool | None = None  # worldcontact: replay each static rollout step as a CUDA graph; unset: params train

    def validate(self) -> None:
        if self.kind in CHECKPOINT_KINDS and not self.path:
            raise ValueError(f"kind {self.kind!r} needs a path (its checkpoint directory)")
        if self.kind not in CHECKPOINT_KINDS and self.path:
            raise ValueError(f"kind {self.kind!r} takes no path, got {self.path!r}")
        for key in WORLDCONTACT_KEYS:
            if getattr(self, key) is not None and self.kind != "worldcontact":
                raise ValueError(f"{key} is a setting of kind 'worldcontact' only, not of kind {self.kind!r}")
        for key in NEWTON_KEYS:
            value = getattr(self, key)
            if value is None:
                continue
            if self.kind != "newton":
                raise ValueError(f"{key} is a setting of kind 'newton' only, not of kind {self.kind!r}")
            if key == "cloth_vertices_scale" and not value > 0:
                raise ValueError(f"{key} must be > 0, got {value}")
            if key != "cloth_vertices_scale" and value < 1:
                raise ValueError(f"{key} must be >= 1, got {value}")


@dataclass(frozen=True)
class EvaluateConfig:
    """Held-out rollouts (Table 1 analogue) and long stability rollouts of every method."""

    rollout_frames: int  # steps of each held-out rollout from a motion phase's start and on the chart (capped)
    stability_frames: int  # steps of each long rollout (>= 100 = 4 s at paper settings; capped by the episode)
    methods: dict[str, MethodSpec]
    stability_per_task: int = 1  # long rollouts per task, from its longest episodes
    penetration_depth_m: float = 0.01  # cloth deeper than this inside table / robot / rigid objects penetrates
    contact_band_m: float = 0.01  # contact area: cloth within this signed distance of any geometry
    divergence_strain: float = 2.0  # a rollout diverges at the first step with max |len/rest - 1| above this ...
    divergence_penetration_pct: float = 25.0  # ... or more than this % of cloth area penetrating, or non-finite
    device: str = "cpu"  # cpu | cuda | cuda:k | auto (the Newton methods simulate on it too)
    seed: int = 0
    chart_max_cases: int | None = None  # held-out rollouts on the speed-accuracy chart, for every method (the
    # Newton methods run on only these: they cost real simulation); None = all
    episode_frames: int = 250  # steps of each held-out span's whole rollout from its first frame (capped by the span)
    phase_starts: int = 4  # held-out rollouts per span from the first frames of its motion phases, spread over them
    subject: str = "worldcontact"  # the method whose whole-episode ratios to the best baseline are summarised

    def validate(self) -> None:
        for name in ("rollout_frames", "stability_frames", "stability_per_task", "episode_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("penetration_depth_m", "contact_band_m", "divergence_strain", "divergence_penetration_pct"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.phase_starts < 0:
            raise ValueError(f"phase_starts must be >= 0, got {self.phase_starts}")
        if self.chart_max_cases is not None and self.chart_max_cases < 1:
            raise ValueError(f"chart_max_cases must be >= 1 or null (all), got {self.chart_max_cases}")
        if not self.methods:
            raise ValueError("methods is empty: name at least one method to evaluate")
        check_device_name(self.device)
