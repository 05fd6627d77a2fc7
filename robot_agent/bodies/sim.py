"""``type = "sim"``: a robot in the embedded simulated world (``sim.robot.SimRobot``).

The scene comes from ``(family, seed)``; the robot follows geodesic paths on the scene's nav grid,
accumulates odometry drift (``OdometryNoise``), and renders its camera from its TRUE pose. Travel
costs are geodesic distances on the nav grid. With ``oracle = true`` each capture carries the
ORACLE ground truth (true pose, instance ids, depth). The simulator is imported only in ``create``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from pydantic import Field

from protocol.messages import Intrinsics, Viewpoint
from robot_agent.bodies.base import BodyConfig, BodyConfigError, BodyStatus, Capture, OracleCapture


class Config(BodyConfig):
    type: Literal["sim"] = Field(default="sim", description="robot in the simulated world")
    family: Literal["apartment", "furnished_room", "apartment_large"] = Field(
        default="apartment", description="scene family"
    )
    seed: int = Field(default=0, ge=0, description="scene seed")
    start: tuple[float, float, float] | None = Field(
        default=None, description="start pose x, y, yaw_rad (default: a viewpoint picked by start_seed)"
    )
    start_seed: int = Field(default=0, ge=0, description="picks the start viewpoint when start is not given")
    width: int = Field(default=640, gt=0, le=4096, description="camera image width, pixels")
    height: int = Field(default=480, gt=0, le=4096, description="camera image height, pixels")
    hfov_deg: float = Field(default=90.0, gt=1, lt=179, description="horizontal field of view, degrees")
    camera_height_m: float = Field(default=1.0, gt=0, description="camera height above the floor")
    camera_pitch_deg: float = Field(default=-15.0, ge=-89, le=89, description="camera tilt (negative: down)")
    robot_radius_m: float = Field(default=0.25, ge=0, description="clearance kept from obstacles")
    nav_cell_m: float = Field(default=0.05, gt=0, description="nav grid cell size")
    speed_mps: float = Field(default=0.5, gt=0, description="driving speed, metres per second of robot time")
    turn_rate_dps: float = Field(default=90.0, gt=0, description="turning speed, degrees per second")
    odom_trans_std_per_m: float = Field(default=0.01, ge=0, description="odometry position drift std per metre")
    odom_rot_std_deg_per_m: float = Field(default=0.5, ge=0, description="odometry heading drift, deg per metre")
    odom_rot_std_deg_per_rad: float = Field(
        default=0.2, ge=0, description="odometry heading drift, deg per radian turned"
    )
    noise_seed: int = Field(default=0, description="odometry noise seed")
    viewpoint_spacing_m: float = Field(default=0.6, gt=0, description="lattice spacing of the viewpoints")
    n_headings: int = Field(default=8, ge=1, le=36, description="headings per viewpoint position")
    max_range_m: float = Field(default=6.0, gt=0, description="useful sensing range announced to planners")
    oracle: bool = Field(default=False, description="also publish ORACLE ground truth (ids, depth, true pose)")


class SimBody:
    def __init__(self, config: Config) -> None:
        try:
            from sim.nav import NavMap
            from sim.render import Renderer
            from sim.robot import OdometryNoise, SimRobot
            from sim.scene import generate_scene
        except ImportError as e:
            raise BodyConfigError(f"the sim body needs the simulator (server extra): {e}") from None
        c = self.config = config
        self.intrinsics = Intrinsics.from_fov(c.width, c.height, c.hfov_deg)
        self.camera_height_m = c.camera_height_m
        self.camera_pitch_deg = c.camera_pitch_deg
        self.max_range_m = c.max_range_m
        self.oracle = c.oracle
        self.scene = generate_scene(c.family, c.seed)
        renderer = Renderer(self.scene)
        self.nav = NavMap(self.scene, robot_radius_m=c.robot_radius_m, cell_m=c.nav_cell_m, renderer=renderer)
        self._viewpoints: list[Viewpoint] = self.nav.viewpoints(c.viewpoint_spacing_m, c.n_headings)
        if c.start is not None:
            start = c.start
            if not self.nav.is_free(start[0], start[1]):
                raise BodyConfigError(f"start pose {start} is not free floor in {c.family} seed {c.seed}")
        else:
            if not self._viewpoints:
                raise BodyConfigError(f"{c.family} seed {c.seed} has no navigable viewpoint")
            vp = self._viewpoints[int(np.random.default_rng(c.start_seed).integers(len(self._viewpoints)))]
            start = (vp.x, vp.y, vp.yaw_rad)
        self.noise = OdometryNoise(c.odom_trans_std_per_m, c.odom_rot_std_deg_per_m, c.odom_rot_std_deg_per_rad)
        self.robot: Any = SimRobot(
            self.scene, self.nav, start, intrinsics=self.intrinsics, camera_height_m=c.camera_height_m,
            camera_pitch_deg=c.camera_pitch_deg, noise=self.noise, seed=c.noise_seed, speed_mps=c.speed_mps,
            turn_rate_rad_s=math.radians(c.turn_rate_dps), renderer=renderer,
        )
        self._labels = {o.obj_id: o.label for o in self.scene.objects}
        self._moving = False

    def pose_odom(self) -> tuple[float, float, float]:
        x, y, yaw = self.robot.pose_odom()
        return float(x), float(y), float(yaw)

    def pose_true(self) -> tuple[float, float, float]:
        x, y, yaw = self.robot.pose_true()
        return float(x), float(y), float(yaw)

    def T_world_cam_odom(self) -> np.ndarray:
        return np.asarray(self.robot.T_world_cam_odom(), dtype=np.float64)

    def pose_covariance(self) -> np.ndarray:
        """The drift model's covariance so far (``sim.robot.SimRobot.odometry_covariance``)."""
        return np.asarray(self.robot.odometry_covariance(), dtype=np.float64)

    def distance_m(self) -> float:
        return float(self.robot.distance_m)

    def viewpoints(self) -> list[Viewpoint]:
        return list(self._viewpoints)

    def travel_costs_m(self, viewpoints: Sequence[Viewpoint]) -> np.ndarray:
        x, y, _ = self.robot.pose_true()
        field = self.nav.distances_from((x, y))
        return np.array([field(v.x, v.y) for v in viewpoints], dtype=np.float64)

    def drive_to(self, x: float, y: float, yaw_rad: float) -> str | None:
        self.stop()
        if not all(math.isfinite(v) for v in (x, y, yaw_rad)):
            return "goal pose is not finite"
        if not self.nav.is_free(x, y):
            return f"goal ({x:.2f}, {y:.2f}) is not free floor (outside the map or inside an obstacle)"
        if not self.robot.drive_to(x, y, yaw_rad):
            self.stop()
            return f"goal ({x:.2f}, {y:.2f}): {self.robot.reason or 'unreachable'}"
        self._moving = True
        return None

    def stop(self) -> None:
        x, y, yaw = self.robot.pose_true()
        self.robot.teleport(x, y, yaw, reset_odometry=False)  # cancels the path, keeps the drift
        self._moving = False

    def step(self, dt_s: float) -> BodyStatus:
        if not self._moving:
            return "idle"
        status = self.robot.step(dt_s)
        if status == "moving":
            return "moving"
        self._moving = False
        return "arrived" if status == "arrived" else "failed"

    def capture(self) -> Capture:
        out = self.robot.render()
        oracle = None
        if self.oracle:
            oracle = OracleCapture(
                T_world_cam_true=np.asarray(self.robot.T_world_cam_true(), dtype=np.float64),
                instance_id=out.instance_id,
                depth_m=out.depth_m,
                labels=self._labels,
            )
        return Capture(rgb=out.rgb, oracle=oracle)

    def close(self) -> None:
        pass


def create(config: Config) -> SimBody:
    return SimBody(config)
