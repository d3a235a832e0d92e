"""The `train` params section: segments, the two learning-rate schedules, validation and devices."""

from __future__ import annotations

from dataclasses import dataclass, replace

from wc.train.selection import SELECT_BY, SHIP_STAGES


@dataclass(frozen=True)
class Schedule:
    """Linear warm-up from `start_lr` to `peak_lr`, then cosine decay to `final_lr` at `steps`."""

    steps: int
    peak_lr: float
    start_lr: float
    final_lr: float
    warmup_steps: int

    def validate(self) -> None:
        if self.steps < 0 or self.warmup_steps < 0:
            raise ValueError("steps and warmup_steps must be >= 0")
        if self.warmup_steps > self.steps:
            raise ValueError(f"warmup_steps ({self.warmup_steps}) exceeds steps ({self.steps})")
        if min(self.peak_lr, self.start_lr, self.final_lr) < 0:
            raise ValueError("learning rates must be >= 0")


@dataclass(frozen=True)
class TrainConfig:
    """Paper: W = 5, λx = λv = 1e4, AdamW (0.9, 0.999), weight decay 5e-4; base then projection fine-tune."""

    base: Schedule  # stage 1: no projection
    projection: Schedule  # stage 2: continues from stage 1 with the topology projection in the loop
    window: int = 5  # W frames per segment: W - 1 autoregressive steps with gradients through all of them
    batch_size: int = 1  # segments per optimisation step (per process), all of one layout
    lambda_x: float = 1.0e4
    lambda_v: float = 1.0e4
    betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = 5.0e-4
    grad_clip: float = 1.0  # max global gradient norm (0 = off)
    input_noise_m: float = 0.0  # random-walk noise std on each window's starting state [m] (wc/train/noise.py; 0 = off)
    smoothing_iterations: int = 4  # projection P: Laplacian smoothing of the displacement
    smoothing_weight: float = 0.35
    constraint_iterations: int = 32  # then edge-length constraints
    edge_ratio: tuple[float, float] = (0.9, 1.1)
    eval_every_steps: int = 50  # validation loss + held-out rollout error, logged as one "epoch"
    val_windows: int = 32  # validation segments per evaluation (a fixed, seeded subset)
    rollout_frames: int = 25  # held-out autoregressive rollout length per validation episode
    select_by: str = "val_loss"  # checkpoint score: val_loss (W-frame windows) | rollout (held-out episodes; wc/train/selection.py)
    event_oversample: float = 0.0  # windows near a contact event drawn 1 + this times as often (wc/train/events.py; 0 = off)
    event_margin_frames: int = 2  # ... within this many frames of one
    event_accel_m_s2: float = 8.0  # a vertex accelerating beyond this between frames is an impact event
    select_max_strain: float = 1.0  # rollout: a rollout with a rest edge stretched beyond this has diverged (never selected)
    ship_stage: str = "best"  # best: the stage whose best checkpoint scores lower | last: the projection stage if it ran
    holdout_fraction: float = 0.25  # with no val split: this share of each train episode validates ...
    holdout_block_frames: int = 12  # ... as interleaved blocks of this many frames (wc.train.data.split_blocks)
    stats_episodes: int = 32  # episodes read to set the input/output scales
    per_axis_scales: bool = False  # one scale per axis (x, y, z) for v, Δx, Δv (gravity and lifts move along z)
    checkpoint_every_steps: int = 100
    autocast_bf16: bool = False  # CUDA only: bf16 autocast of the network, fp32 state accumulation
    tf32: bool = False  # CUDA only: TF32 matrix products outside autocast
    num_workers: int = 0  # DataLoader workers (reference path only)
    # The static-shape path (wc/train/static_step.py): training frames resident on the device, windows gathered by
    # index, fixed-K neighbour slots (capacities from the data with this headroom, grown on overflow), batched
    # validation; `compile` (torch.compile of each frame step) and `cuda_graph` (CUDA only) build on it.
    static: bool = False
    compile: bool = False
    compile_dynamic: bool = False  # True: one graph for every layout and batch size (its backward compiles slowly)
    cuda_graph: bool = False
    neighbor_headroom: float = 1.25
    max_minutes: float = 0.0  # stop cleanly with a complete checkpoint after this wall time (0 = no limit); --resume goes on
    device: str = "cpu"  # cpu | cuda | cuda:k (torchrun: each process takes cuda:LOCAL_RANK)
    init_from: str = ""  # "" = from scratch; else fine-tune a pretrained checkpoint: a path or hf://owner/repo/file
    fine_tune_lr_scale: float = 1.0  # with init_from: both schedules' learning rates times this (gentler steps)
    seed: int = 0

    def run_config(self) -> "TrainConfig":
        """The config a run trains with: from a pretrained checkpoint (`init_from`), every learning rate of both
        schedules times `fine_tune_lr_scale`; from scratch, this config itself."""
        if not self.init_from or self.fine_tune_lr_scale == 1.0:
            return self
        k = self.fine_tune_lr_scale
        scaled = [replace(s, peak_lr=s.peak_lr * k, start_lr=s.start_lr * k, final_lr=s.final_lr * k)
                  for s in (self.base, self.projection)]
        return replace(self, base=scaled[0], projection=scaled[1])

    def validate(self) -> None:
        if self.window < 2:
            raise ValueError(f"window must be >= 2 frames, got {self.window}")
        if self.batch_size < 1:
            raise ValueError("batch_size must be >= 1")
        if not 0.0 < self.holdout_fraction < 1.0:
            raise ValueError(f"holdout_fraction must be in (0, 1), got {self.holdout_fraction}")
        lo, hi = self.edge_ratio
        if not 0 < lo <= 1 <= hi:
            raise ValueError(f"edge_ratio must satisfy 0 < lo <= 1 <= hi, got {self.edge_ratio}")
        if (self.compile or self.cuda_graph) and not self.static:
            raise ValueError("train.compile and train.cuda_graph need the static-shape path (train.static: true)")
        if self.neighbor_headroom < 1.0:
            raise ValueError(f"neighbor_headroom must be >= 1, got {self.neighbor_headroom}")
        if self.input_noise_m < 0:
            raise ValueError(f"input_noise_m must be >= 0 m, got {self.input_noise_m}")
        if self.event_oversample < 0 or self.event_margin_frames < 0 or not self.event_accel_m_s2 > 0:
            raise ValueError(f"event_oversample and event_margin_frames must be >= 0 and event_accel_m_s2 positive, got "
                             f"{self.event_oversample}, {self.event_margin_frames}, {self.event_accel_m_s2}")
        if self.select_by not in SELECT_BY:
            raise ValueError(f"select_by must be one of {SELECT_BY}, got {self.select_by!r}")
        if self.ship_stage not in SHIP_STAGES:
            raise ValueError(f"ship_stage must be one of {SHIP_STAGES}, got {self.ship_stage!r}")
        if not self.select_max_strain > 0:
            raise ValueError(f"select_max_strain must be positive, got {self.select_max_strain}")
        if not self.fine_tune_lr_scale > 0:
            raise ValueError(f"fine_tune_lr_scale must be positive, got {self.fine_tune_lr_scale}")
        if self.max_minutes < 0:
            raise ValueError(f"max_minutes must be >= 0 (0 = no limit), got {self.max_minutes}")
        for name in ("eval_every_steps", "val_windows", "holdout_block_frames", "rollout_frames", "stats_episodes", "checkpoint_every_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
