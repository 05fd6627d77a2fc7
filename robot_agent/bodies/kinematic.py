"""``type = "kinematic"``: a light stand-in base in an empty rectangular room, no simulator needed.

It drives straight lines (turn, go, turn) at a set speed inside ``bounds_m`` around rectangular
``obstacles``, integrates odometry with seeded noise, and "renders" a cheap synthetic image from
its true pose. For dry runs of a deployment (router, planner, mapper wiring) on any machine and for
fast tests of the agent; it is not a world model (use ``sim`` for that).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from protocol.messages import Intrinsics, Viewpoint
from protocol.poses import camera_pose_from_base, wrap_angle
from robot_agent.bodies.base import BodyConfig, BodyConfigError, BodyStatus, Capture

Rect = tuple[float, float, float, float]


class Config(BodyConfig):
    type: Literal["kinematic"] = Field(default="kinematic", description="straight-line stand-in base")
    bounds_m: Rect = Field(default=(0.0, 0.0, 6.0, 4.0), description="room rectangle xmin, ymin, xmax, ymax")
    obstacles: list[Rect] = Field(default_factory=list, description="blocked rectangles xmin, ymin, xmax, ymax")
    robot_radius_m: float = Field(default=0.25, ge=0, description="clearance kept from walls and obstacles")
    start: tuple[float, float, float] | None = Field(
        default=None, description="start pose x, y, yaw_rad (default: room centre facing +x)"
    )
    speed_mps: float = Field(default=0.5, gt=0, description="driving speed, metres per second of robot time")
    turn_rate_dps: float = Field(default=90.0, gt=0, description="turning speed, degrees per second")
    width: int = Field(default=160, gt=0, le=4096, description="camera image width, pixels")
    height: int = Field(default=120, gt=0, le=4096, description="camera image height, pixels")
    hfov_deg: float = Field(default=90.0, gt=1, lt=179, description="horizontal field of view, degrees")
    camera_height_m: float = Field(default=1.0, gt=0, description="camera height above the floor")
    camera_pitch_deg: float = Field(default=-15.0, ge=-89, le=89, description="camera tilt (negative: down)")
    max_range_m: float = Field(default=6.0, gt=0, description="useful sensing range announced to planners")
    viewpoint_spacing_m: float = Field(default=1.0, gt=0, description="grid spacing of the viewpoints")
    n_headings: int = Field(default=4, ge=1, le=36, description="headings per viewpoint position")
    odom_trans_sigma: float = Field(
        default=0.01, ge=0, description="odometry position noise std per sqrt(metre) travelled"
    )
    odom_yaw_sigma: float = Field(default=0.005, ge=0, description="odometry heading noise std, rad per sqrt(m)")
    seed: int = Field(default=0, description="odometry noise seed")

    @field_validator("bounds_m", "obstacles")
    @classmethod
    def _ordered(cls, v: Rect | list[Rect]) -> Rect | list[Rect]:
        for r in v if isinstance(v, list) else [v]:
            if not (r[0] < r[2] and r[1] < r[3]):
                raise ValueError(f"rectangle {r} needs xmin < xmax and ymin < ymax")
        return v



class KinematicBody:
    def __init__(self, config: Config) -> None:
        self.config = c = config
        self.intrinsics = Intrinsics.from_fov(c.width, c.height, c.hfov_deg)
        self.camera_height_m = c.camera_height_m
        self.camera_pitch_deg = c.camera_pitch_deg
        self.max_range_m = c.max_range_m
        self.oracle = False
        x0, y0, x1, y1 = c.bounds_m
        start = c.start if c.start is not None else ((x0 + x1) / 2, (y0 + y1) / 2, 0.0)
        if not self.is_free(start[0], start[1]):
            raise BodyConfigError(f"start pose {start} is not in free space")
        self._true = [float(start[0]), float(start[1]), float(start[2])]
        self._odom = list(self._true)
        self._rng = np.random.default_rng(c.seed)
        self._var_xy = 0.0
        self._var_yaw = 0.0
        self._distance = 0.0
        self._plan: list[tuple[str, float, float]] = []  # ("turn", yaw, _) / ("go", x, y)
        self._status: BodyStatus = "idle"
        self._viewpoints = self._make_viewpoints()

    # --- geometry --------------------------------------------------------------------------
    def is_free(self, x: float, y: float) -> bool:
        c = self.config
        r = c.robot_radius_m
        x0, y0, x1, y1 = c.bounds_m
        if not (x0 + r <= x <= x1 - r and y0 + r <= y <= y1 - r):
            return False
        return not any(a - r <= x <= b + r and lo - r <= y <= hi + r for a, lo, b, hi in c.obstacles)

    def _segment_free(self, x0: float, y0: float, x1: float, y1: float) -> bool:
        n = max(2, int(math.hypot(x1 - x0, y1 - y0) / 0.05) + 1)
        return all(self.is_free(x0 + (x1 - x0) * t, y0 + (y1 - y0) * t) for t in np.linspace(0, 1, n))

    def _make_viewpoints(self) -> list[Viewpoint]:
        c = self.config
        x0, y0, x1, y1 = c.bounds_m
        s = c.viewpoint_spacing_m
        out: list[Viewpoint] = []
        for x in np.arange(x0 + s / 2, x1, s):
            for y in np.arange(y0 + s / 2, y1, s):
                if not self.is_free(float(x), float(y)):
                    continue
                for k in range(c.n_headings):
                    yaw = wrap_angle(2 * math.pi * k / c.n_headings)
                    out.append(Viewpoint(vp_id=len(out), x=float(x), y=float(y), yaw_rad=yaw, room="room"))
        return out

    # --- RobotBody -------------------------------------------------------------------------
    def pose_odom(self) -> tuple[float, float, float]:
        return (self._odom[0], self._odom[1], self._odom[2])

    def pose_true(self) -> tuple[float, float, float]:
        return (self._true[0], self._true[1], self._true[2])

    def T_world_cam_odom(self) -> np.ndarray:
        x, y, yaw = self._odom
        return camera_pose_from_base(x, y, yaw, self.camera_height_m, self.camera_pitch_deg)

    def pose_covariance(self) -> np.ndarray:
        return np.diag([self._var_xy, self._var_xy, 1e-6, 1e-6, 1e-6, self._var_yaw + 1e-8])

    def distance_m(self) -> float:
        return self._distance

    def viewpoints(self) -> list[Viewpoint]:
        return list(self._viewpoints)

    def travel_costs_m(self, viewpoints: Sequence[Viewpoint]) -> np.ndarray:
        x, y, _ = self._true
        return np.array(
            [math.hypot(v.x - x, v.y - y) if self._segment_free(x, y, v.x, v.y) else math.inf for v in viewpoints],
            dtype=np.float64,
        )

    def drive_to(self, x: float, y: float, yaw_rad: float) -> str | None:
        self.stop()
        if not all(math.isfinite(v) for v in (x, y, yaw_rad)):
            return "goal pose is not finite"
        if not self.is_free(x, y):
            return f"goal ({x:.2f}, {y:.2f}) is outside the free space"
        x0, y0, _ = self._true
        if not self._segment_free(x0, y0, x, y):
            return f"no straight path from ({x0:.2f}, {y0:.2f}) to ({x:.2f}, {y:.2f})"
        plan: list[tuple[str, float, float]] = []
        if math.hypot(x - x0, y - y0) > 1e-6:
            plan += [("turn", math.atan2(y - y0, x - x0), 0.0), ("go", x, y)]
        plan.append(("turn", wrap_angle(yaw_rad), 0.0))
        self._plan = plan
        self._status = "moving"
        return None

    def stop(self) -> None:
        self._plan = []
        if self._status == "moving":
            self._status = "idle"

    def _advance(self, dx: float, dy: float, dyaw: float) -> None:
        ds = math.hypot(dx, dy)
        self._true[0] += dx
        self._true[1] += dy
        self._true[2] = wrap_angle(self._true[2] + dyaw)
        self._distance += ds
        # Odometry integrates the same motion in its own (drifting) heading, with noise per sqrt(ds).
        c = self.config
        err_yaw = self._odom[2] - (self._true[2] - dyaw)
        ce, se = math.cos(err_yaw), math.sin(err_yaw)
        nx, ny = self._rng.normal(0.0, c.odom_trans_sigma * math.sqrt(ds), 2) if ds > 0 else (0.0, 0.0)
        self._odom[0] += ce * dx - se * dy + nx
        self._odom[1] += se * dx + ce * dy + ny
        nyaw = self._rng.normal(0.0, c.odom_yaw_sigma * math.sqrt(ds)) if ds > 0 else 0.0
        self._odom[2] = wrap_angle(self._odom[2] + dyaw + nyaw)
        self._var_xy += c.odom_trans_sigma**2 * ds
        self._var_yaw += c.odom_yaw_sigma**2 * ds

    def step(self, dt_s: float) -> BodyStatus:
        if self._status != "moving":
            status, self._status = self._status, "idle"
            return status if status in ("arrived", "failed") else "idle"
        c = self.config
        budget = max(0.0, dt_s)
        while self._plan and budget > 0:
            kind, a, b = self._plan[0]
            if kind == "turn":
                d = wrap_angle(a - self._true[2])
                max_turn = math.radians(c.turn_rate_dps) * budget
                turn = max(-max_turn, min(max_turn, d))
                self._advance(0.0, 0.0, turn)
                budget -= abs(turn) / math.radians(c.turn_rate_dps)
                if abs(d - turn) < 1e-9:
                    self._plan.pop(0)
            else:
                dx, dy = a - self._true[0], b - self._true[1]
                dist = math.hypot(dx, dy)
                go = min(dist, c.speed_mps * budget)
                if dist > 0:
                    self._advance(dx / dist * go, dy / dist * go, 0.0)
                budget -= go / c.speed_mps
                if dist - go < 1e-9:
                    self._plan.pop(0)
        if not self._plan:
            self._status = "idle"
            return "arrived"
        return "moving"

    def capture(self) -> Capture:
        """A synthetic view: colour by world bearing of each column, shade by row, from the TRUE pose."""
        c, K = self.config, self.intrinsics
        x, y, yaw = self._true
        u = np.arange(c.width, dtype=np.float64)
        bearing = yaw - np.arctan2(u - K.cx, K.fx)  # camera x is to the right = clockwise
        hue = (np.degrees(bearing) % 360.0) / 360.0
        stripes = 0.5 + 0.5 * np.sin(bearing * 12.0 + 3.0 * x + 2.0 * y)
        v = np.linspace(1.0, 0.4, c.height)[:, None]
        r = 0.5 + 0.5 * np.cos(2 * np.pi * hue)
        g = 0.5 + 0.5 * np.cos(2 * np.pi * (hue - 1 / 3))
        b = 0.5 + 0.5 * np.cos(2 * np.pi * (hue - 2 / 3))
        rgb = np.stack([r * stripes, g * stripes, b], axis=-1)[None, :, :] * v[:, :, None]
        return Capture(rgb=(np.clip(rgb, 0, 1) * 255).astype(np.uint8))

    def close(self) -> None:
        pass


def create(config: Config) -> KinematicBody:
    return KinematicBody(config)
