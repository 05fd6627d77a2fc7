"""A simulated robot base: follows nav paths, accumulates odometry drift, renders its camera.

Odometry is a random walk on top of the true motion: per metre travelled the position error grows
with std ``trans_std_per_m`` (per axis) and the heading error with ``rot_std_deg_per_m``; turning in
place adds ``rot_std_deg_per_rad`` per radian. With all three at 0, odometry equals the truth exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol.messages import Intrinsics
from protocol.poses import camera_pose_from_base, wrap_angle


@dataclass(frozen=True)
class OdometryNoise:
    """Odometry drift model (random walk; standard deviations per metre / radian of true motion)."""

    trans_std_per_m: float = 0.01
    rot_std_deg_per_m: float = 0.5
    rot_std_deg_per_rad: float = 0.2

    @classmethod
    def none(cls) -> OdometryNoise:
        return cls(0.0, 0.0, 0.0)

    @property
    def is_zero(self) -> bool:
        return self.trans_std_per_m == 0 and self.rot_std_deg_per_m == 0 and self.rot_std_deg_per_rad == 0


def _se2(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _xyyaw(M: np.ndarray) -> tuple[float, float, float]:
    return float(M[0, 2]), float(M[1, 2]), float(math.atan2(M[1, 0], M[0, 0]))



class SimRobot:
    """A differential-drive-like base: turns in place towards each path segment, then drives it."""

    def __init__(self, scene: Any, nav: Any, start_xy_yaw: tuple[float, float, float],
                 intrinsics: Intrinsics | None = None, camera_height_m: float = 1.0,
                 camera_pitch_deg: float = -15.0, noise: OdometryNoise | None = None, seed: int = 0,
                 speed_mps: float = 0.5, turn_rate_rad_s: float = 1.5, renderer: Any = None):
        if speed_mps <= 0 or turn_rate_rad_s <= 0:
            raise ValueError("speed_mps and turn_rate_rad_s must be > 0")
        self.scene = scene
        self.nav = nav
        self.intrinsics = intrinsics or Intrinsics.from_fov(640, 480, 90.0)
        self.camera_height_m = float(camera_height_m)
        self.camera_pitch_deg = float(camera_pitch_deg)
        self.noise = noise if noise is not None else OdometryNoise()
        self.speed_mps = float(speed_mps)
        self.turn_rate_rad_s = float(turn_rate_rad_s)
        self._rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x0D0])
        self._renderer = renderer
        x, y, yaw = (float(v) for v in start_xy_yaw)
        self._true = (x, y, wrap_angle(yaw))
        self._drift = np.eye(3)  # T_odom = drift @ T_true
        self.status = "idle"
        self.reason: str | None = None
        self.distance_m = 0.0
        self.turned_rad = 0.0  # total absolute heading change, radians (turn-in-place drift grows with it)
        self.steps = 0
        self._path: np.ndarray | None = None
        self._wp = 0
        self._goal_yaw: float | None = None

    # -- poses ----------------------------------------------------------------------------------
    def pose_true(self) -> tuple[float, float, float]:
        return self._true

    def pose_odom(self) -> tuple[float, float, float]:
        if np.array_equal(self._drift, np.eye(3)):
            return self._true
        return _xyyaw(self._drift @ _se2(*self._true))

    def T_world_cam_true(self) -> np.ndarray:
        x, y, yaw = self.pose_true()
        return camera_pose_from_base(x, y, yaw, self.camera_height_m, self.camera_pitch_deg)

    def T_world_cam_odom(self) -> np.ndarray:
        x, y, yaw = self.pose_odom()
        return camera_pose_from_base(x, y, yaw, self.camera_height_m, self.camera_pitch_deg)

    def teleport(self, x: float, y: float, yaw: float, reset_odometry: bool = True) -> None:
        """Put the robot somewhere (a new episode); odometry restarts from the truth by default."""
        self._true = (float(x), float(y), wrap_angle(float(yaw)))
        if reset_odometry:
            self._drift = np.eye(3)
        self._path, self._goal_yaw = None, None
        self.status, self.reason = "idle", None

    # -- motion ---------------------------------------------------------------------------------
    def drive_to(self, x: float, y: float, yaw: float) -> bool:
        """Plan a path from the true pose to (x, y) and start driving; False (status 'refused') when the
        goal is not reachable free floor."""
        path = self.nav.path(self._true[:2], (float(x), float(y)))
        if path is None:
            self.status, self.reason = "refused", "goal unreachable or not free floor"
            self._path = None
            return False
        self._path = path
        self._wp = 1
        self._goal_yaw = wrap_angle(float(yaw))
        self.status, self.reason = "moving", None
        return True

    def odometry_covariance(self) -> np.ndarray:
        """The 6x6 covariance (x y z roll pitch yaw; m^2, rad^2) of the drift model's random walk so far, as a
        robot declares it in its frame headers: position variance grows with the distance driven, heading
        variance with the distance and the angle turned, so its growth between two frames is the drift between
        them (what the mapper reads). The position error that an earlier heading error causes is left out: it is
        shared by nearby frames (their relative pose hardly has it), and counting it would make two frames
        0.3 m apart after a 50 m drive look 0.2 m uncertain relative to each other."""
        n, d = self.noise, self.distance_m
        var_yaw = (math.radians(n.rot_std_deg_per_m) ** 2 * d
                   + math.radians(n.rot_std_deg_per_rad) ** 2 * self.turned_rad)
        var_xy = n.trans_std_per_m**2 * d
        return np.diag([var_xy, var_xy, 1e-6, 1e-6, 1e-6, var_yaw + 1e-8])

    def step(self, dt_s: float) -> str:
        """Advance the current motion by ``dt_s`` seconds of simulated time; returns the status."""
        if self.status != "moving" or self._path is None:
            return self.status
        budget = max(float(dt_s), 0.0)
        while budget > 1e-12 and self.status == "moving":
            x, y, yaw = self._true
            if self._wp < len(self._path):
                tx, ty = self._path[self._wp]
                dx, dy = tx - x, ty - y
                dist = math.hypot(dx, dy)
                if dist < 1e-9:
                    self._wp += 1
                    continue
                want = math.atan2(dy, dx)
                dyaw = wrap_angle(want - yaw)
                if abs(dyaw) > 1e-6:
                    turn = math.copysign(min(abs(dyaw), self.turn_rate_rad_s * budget), dyaw)
                    budget -= abs(turn) / self.turn_rate_rad_s
                    self._move(x, y, wrap_angle(yaw + turn) if abs(turn) < abs(dyaw) else want)
                    continue
                d = min(dist, self.speed_mps * budget)
                budget -= d / self.speed_mps
                if d >= dist:
                    self._move(float(tx), float(ty), want)
                    self._wp += 1
                else:
                    self._move(x + dx / dist * d, y + dy / dist * d, want)
            else:
                assert self._goal_yaw is not None
                dyaw = wrap_angle(self._goal_yaw - yaw)
                if abs(dyaw) <= 1e-9:
                    self._move(x, y, self._goal_yaw)
                    self.status = "arrived"
                    self.steps += 1
                    break
                turn = math.copysign(min(abs(dyaw), self.turn_rate_rad_s * budget), dyaw)
                budget -= abs(turn) / self.turn_rate_rad_s
                self._move(x, y, self._goal_yaw if abs(turn) >= abs(dyaw) else wrap_angle(yaw + turn))
        return self.status

    def run_to_arrival(self, dt_s: float = 0.1, max_s: float = 600.0) -> str:
        """Step until the current goal is reached (or ``max_s`` simulated seconds pass)."""
        t = 0.0
        while self.status == "moving" and t < max_s:
            self.step(dt_s)
            t += dt_s
        return self.status

    def _move(self, x: float, y: float, yaw: float) -> None:
        x0, y0, yaw0 = self._true
        self._true = (x, y, wrap_angle(yaw))
        ds = math.hypot(x - x0, y - y0)
        dth = abs(wrap_angle(yaw - yaw0))
        self.distance_m += ds
        self.turned_rad += dth
        if self.noise.is_zero or (ds == 0 and dth == 0):
            return
        n = self.noise
        ex, ey = self._rng.normal(0.0, n.trans_std_per_m * math.sqrt(ds), 2)
        var_yaw = math.radians(n.rot_std_deg_per_m) ** 2 * ds + math.radians(n.rot_std_deg_per_rad) ** 2 * dth
        eth = float(self._rng.normal(0.0, math.sqrt(var_yaw)))
        # T_odom' = T_odom @ inc @ e  =>  drift' = drift @ T_true' @ e @ inv(T_true')
        Tn = _se2(*self._true)
        self._drift = self._drift @ Tn @ _se2(float(ex), float(ey), eth) @ np.linalg.inv(Tn)

    # -- sensing --------------------------------------------------------------------------------
    @property
    def renderer(self) -> Any:
        if self._renderer is None:
            self._renderer = getattr(self.nav, "renderer", None)
            if self._renderer is None:
                from sim.render import Renderer

                self._renderer = Renderer(self.scene)
        return self._renderer

    def render(self) -> Any:
        """What the camera sees from the TRUE pose (RGB, depth, instance ids)."""
        return self.renderer.render(self.intrinsics, self.T_world_cam_true())
