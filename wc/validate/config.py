"""Tolerances of the episode checks (`validate:` in params.yaml)."""

from __future__ import annotations

from dataclasses import dataclass

from wc.devices import check_device_name

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class ValidateConfig:
    max_speed_m_s: float  # blow-up: any vertex faster than this
    max_edge_strain: float  # blow-up: rest edge stretched beyond (length / rest length - 1)
    penetration_tol_m: float  # a cloth vertex deeper than this inside the table, a robot box or a rigid object
    self_intersection_every: int  # check triangle-triangle crossings on every k-th frame (0, k, 2k, ...)
    release_opening_m: float  # a gripper counts as released when its opening rises past this
    adhesion_radius_m: float  # cloth vertices this close to a finger pad at release are watched
    adhesion_window_s: float  # ... and checked this long after the release
    adhesion_rise_m: float  # ... failing if they and the fingers both rose more than this
    workspace_min_m: Vec3  # axis-aligned workspace box, world frame
    workspace_max_m: Vec3
    min_visible_fraction: float  # of cloth vertices projecting inside the view camera's image
    val_per_task: int  # accepted episodes per task put in the val split (see wc.validate.split)
    test_per_task: int  # ... and in the test split (filled before val; >= 1 train episode is always kept)
    split_seed: int  # seed of the per-task shuffle that assigns the splits
    view_camera: str = "top"
    train_on_task_failures: bool = False  # keep episodes that pass every physical check but fail their task (a strap
    # that slipped, a bag dropped) in the train split, `accepted` false: the world model learns failures too, and
    # every consumer of accepted episodes (expand's sources, render, the policy dataset) still skips them
    device: str = "cpu"  # warp device of the self-intersection check (cpu | cuda[:N] | auto): per frame a BVH over
    # the cloth and a ray cast per edge; at paper size (20k vertices) ~0.14 s a frame on one CPU core

    def validate(self) -> None:
        for name in ("max_speed_m_s", "max_edge_strain", "penetration_tol_m", "self_intersection_every",
                     "release_opening_m", "adhesion_radius_m", "adhesion_window_s", "adhesion_rise_m",
                     "min_visible_fraction"):
            if not getattr(self, name) > 0:
                raise ValueError(f"validate.{name} must be positive, got {getattr(self, name)}")
        if not self.min_visible_fraction <= 1:
            raise ValueError(f"validate.min_visible_fraction must be <= 1, got {self.min_visible_fraction}")
        for name in ("val_per_task", "test_per_task", "split_seed"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"validate.{name} must be >= 0, got {getattr(self, name)}")
        check_device_name(self.device, "validate.device")
        if len(self.workspace_min_m) != 3 or len(self.workspace_max_m) != 3:
            raise ValueError("validate.workspace_min_m and workspace_max_m need 3 values (x, y, z)")
        if not all(lo < hi for lo, hi in zip(self.workspace_min_m, self.workspace_max_m)):
            raise ValueError(f"validate.workspace_min_m {self.workspace_min_m} must be below "
                             f"workspace_max_m {self.workspace_max_m} on every axis")
