"""The `baselines` params section: which baselines to train, their particle counts, radii and optimisers."""

from __future__ import annotations

from dataclasses import dataclass

SELECT_BY = ("val_loss", "rollout")


@dataclass(frozen=True)
class BaselineParams:
    """One baseline's scene-scaled numbers (README.md says how each was scaled from the original).

    particles: object particles per scene layout (FPS over mesh vertices); neighbor_radius_m:
    particle-particle relation radius; tool_radius_m: tool -> particle radius (RoboCraft: the
    original's extra margin over neighbor_radius_m; 0 where the original has none); max_step_m:
    per-step displacement bound per axis (0: the original has none).
    """

    particles: int
    steps: int
    lr: float
    batch: int
    neighbor_radius_m: float
    tool_radius_m: float = 0.0
    max_step_m: float = 0.0
    tool_points_per_body: int = 16  # FPS points kept per robot link / finger / held object (table: all)

    def validate(self) -> None:
        for key in ("particles", "steps", "batch", "tool_points_per_body"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} must be >= 1, got {getattr(self, key)}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        if not self.neighbor_radius_m > 0:
            raise ValueError(f"neighbor_radius_m must be > 0, got {self.neighbor_radius_m}")
        if self.tool_radius_m < 0 or self.max_step_m < 0:
            raise ValueError("tool_radius_m and max_step_m must be >= 0")


@dataclass(frozen=True)
class BaselinesConfig:
    """Baselines trained by the train_baselines stage (wc/baselines/baselines_stage.py), on the split and holdout
    rule of the `train` section.

    `names` are registry names (wc.baselines.BASELINES); each needs its entry in `models`.
    """

    names: tuple[str, ...]
    models: dict[str, BaselineParams]
    eval_every_steps: int = 25  # validation particle loss (RoboCook's plateau schedule steps on it)
    val_windows: int = 8
    rollout_frames: int = 25  # held-out vertex rollout per validation phase, at the end ...
    rollout_phases: int = 8  # ... over this many validation phases (spread evenly over the list)
    device: str = "cpu"
    seed: int = 0
    max_minutes: float = 0.0  # wall-time budget per baseline (0 = none): stops after the step that passes it
    patience_evals: int = 0  # stop once the validation score has not improved for this many evals (0 = never):
    # "trained to convergence"; the weights of the best validation score are the ones saved
    # WorldContact's training recipe, each a switch (off: the originals' recipe; the report records them):
    input_noise: bool = False  # random-walk noise of std train.input_noise_m on each window's observed frames
    event_oversample: bool = False  # windows near a contact event drawn 1 + train.event_oversample times as often
    select_by: str = "val_loss"  # val_loss | rollout: the weights kept are those of the best validation particle
    # loss, or of the lowest held-out rollout position MSE (rollout_frames steps of rollout_phases validation phases)

    def validate(self) -> None:
        if not self.names:
            raise ValueError("names must list at least one baseline")
        for name in self.names:
            if name not in self.models:
                raise ValueError(f"models.{name} missing (names lists it)")
        for key in ("eval_every_steps", "val_windows", "rollout_frames", "rollout_phases"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} must be >= 1, got {getattr(self, key)}")
        if self.select_by not in SELECT_BY:
            raise ValueError(f"select_by must be one of {SELECT_BY}, got {self.select_by!r}")
        if self.max_minutes < 0 or self.patience_evals < 0:
            raise ValueError(f"max_minutes and patience_evals must be >= 0 (0 = off), got {self.max_minutes}, "
                             f"{self.patience_evals}")
