"""Params of the scene (`scene:` in params.yaml): object sizes, resolutions, table, robot, cameras."""

from __future__ import annotations

from dataclasses import dataclass

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


def _positive(**values: float) -> None:
    for name, value in values.items():
        if not value > 0:
            raise ValueError(f"{name} must be positive, got {value}")


@dataclass(frozen=True)
class BagConfig:
    target_vertices: int  # mesh resolution (paper: 20,274)
    width_m: float
    depth_m: float
    height_m: float
    handle_width_m: float
    handle_rise_m: float
    tag: int

    def validate(self) -> None:
        _positive(target_vertices=self.target_vertices, width_m=self.width_m, depth_m=self.depth_m,
                  height_m=self.height_m, handle_width_m=self.handle_width_m, handle_rise_m=self.handle_rise_m)


@dataclass(frozen=True)
class SphereConfig:
    radius_m: float
    target_vertices: int  # paper: 951
    tag: int

    def validate(self) -> None:
        _positive(radius_m=self.radius_m, target_vertices=self.target_vertices)


@dataclass(frozen=True)
class CubeConfig:
    half_extent_m: float
    target_vertices: int  # paper: 465
    tag: int

    def validate(self) -> None:
        _positive(half_extent_m=self.half_extent_m, target_vertices=self.target_vertices)


@dataclass(frozen=True)
class TableConfig:
    center_m: Vec3
    half_extents_m: Vec3
    tag: int
    sample_region_center_m: Vec2  # environment samples only where objects can touch the table
    sample_region_half_m: Vec2
    sample_spacing_m: float  # paper: ~16,900 samples

    def validate(self) -> None:
        _positive(sample_spacing_m=self.sample_spacing_m, half_x=self.half_extents_m[0],
                  half_y=self.half_extents_m[1], half_z=self.half_extents_m[2])

    @property
    def top_z(self) -> float:
        return self.center_m[2] + self.half_extents_m[2]


@dataclass(frozen=True)
class RobotConfig:
    left_base_xyz_yaw_deg: tuple[float, float, float, float]
    right_base_xyz_yaw_deg: tuple[float, float, float, float]
    sampled_links: tuple[str, ...]  # links whose surfaces get controllable samples
    sample_spacing_m: float  # paper: ~1,114 gripper samples
    left_tag: int  # link k of the left arm gets tag left_tag + k
    right_tag: int
    home_q: tuple[float, float, float, float, float, float]  # joints 1..6 [rad]
    idle_q: tuple[float, float, float, float, float, float] | None = None  # the arm a one-arm task leaves [rad]

    def validate(self) -> None:
        _positive(sample_spacing_m=self.sample_spacing_m)
        if not self.sampled_links:
            raise ValueError("sampled_links must name at least one link")
        if self.idle_q is not None:
            from wc.scene.piper import JOINT_LIMITS  # noqa: PLC0415 (torch, for this check only)
            low, high = JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1]
            if not all(lo <= q <= hi for q, lo, hi in zip(self.idle_q, low, high)):
                raise ValueError(f"robot.idle_q {list(self.idle_q)} is outside the PiPER's joint limits "
                                 f"{JOINT_LIMITS.tolist()} rad")


@dataclass(frozen=True)
class CameraConfig:
    width: int
    height: int
    fov_deg: float  # vertical field of view
    position_m: Vec3  # world position, or offset in the parent link's frame
    look_at_m: Vec3  # world point, or point in the parent link's frame
    up: Vec3
    link: str | None = None  # parent body (e.g. right_link6); None = fixed in the world

    def validate(self) -> None:
        _positive(width=self.width, height=self.height, fov_deg=self.fov_deg)


@dataclass(frozen=True)
class SceneConfig:
    bag: BagConfig
    sphere: SphereConfig
    cube: CubeConfig
    table: TableConfig
    robot: RobotConfig
    cameras: dict[str, CameraConfig]
