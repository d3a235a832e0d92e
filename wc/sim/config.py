"""Params of the Newton source simulator (`sim:` in params.yaml)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ClothMaterial:
    density_kg_m2: float
    tri_ke: float  # membrane stretch stiffness
    tri_ka: float  # membrane area stiffness
    tri_kd: float  # membrane damping
    edge_ke: float  # bending stiffness
    edge_kd: float  # bending damping
    particle_radius_m: float  # contact thickness against bodies
    friction: float

    def validate(self) -> None:
        if not (self.density_kg_m2 > 0 and self.particle_radius_m > 0):
            raise ValueError("cloth density_kg_m2 and particle_radius_m must be positive")


@dataclass(frozen=True)
class RigidMaterial:
    density_kg_m3: float
    friction: float

    def validate(self) -> None:
        if not self.density_kg_m3 > 0:
            raise ValueError("density_kg_m3 must be positive")


@dataclass(frozen=True)
class SimConfig:
    device: str  # "cpu", "cuda", "cuda:0", or "auto" (cuda when present)
    dt_s: float  # solver step (paper: 0.002 s)
    substeps: int  # solver steps per recorded frame (paper: 20 -> frame dt 0.04 s)
    iterations: int  # VBD iterations per step
    friction_epsilon: float  # VBD friction smoothing; below it static friction turns viscous (grip creep)
    self_contact: bool
    self_contact_margin_m: float
    self_contact_gap_m: float
    soft_contact_ke: float  # cloth-body contact stiffness
    soft_contact_kd: float
    soft_contact_gap_m: float  # cloth-body contact detection margin
    robot_friction: float
    table_friction: float
    settle_s: float  # free settling before frame 0
    worlds: int  # episodes simulated at once as separate Newton worlds
    bag: ClothMaterial
    sphere: RigidMaterial
    cube: RigidMaterial
    self_contact_filter_rings: int = 2  # self-contact skips element pairs this many mesh rings apart or closer (Newton's default 2)
    body_particle_contact_buffer: int = 256  # VBD per-body list of cloth contact candidates (Newton's default 256).
    # Overflowing it is not wrong (Newton then scans all stored contacts) but slower, and prints a warning per step
    body_contact_buffer: int = 64  # VBD per-body list of rigid body-body contacts (Newton's default 64); contacts
    # beyond it are dropped (a cube on the table under the gripper reached 138), with a warning per step

    def validate(self) -> None:
        if not self.dt_s > 0:
            raise ValueError(f"dt_s must be positive, got {self.dt_s}")
        for name in ("substeps", "iterations", "worlds"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("body_particle_contact_buffer", "body_contact_buffer"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.self_contact_filter_rings < 0:
            raise ValueError(f"self_contact_filter_rings must be >= 0, got {self.self_contact_filter_rings}")
        if self.settle_s < 0:
            raise ValueError(f"settle_s must be >= 0, got {self.settle_s}")

    @property
    def frame_dt_s(self) -> float:
        return self.dt_s * self.substeps
