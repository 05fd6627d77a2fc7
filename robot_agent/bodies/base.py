"""The robot body contract: what the agent needs from a base with a camera."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from protocol.messages import Intrinsics, Viewpoint
from protocol.oracle import OracleCapture

BodyStatus = Literal["idle", "moving", "arrived", "failed"]


class BodyConfigError(ValueError):
    """A body configuration that can never work (the process exits with a clear message)."""


class BodyConfig(BaseModel):
    """Base of every body backend's config; ``type`` picks the backend in the registry."""

    model_config = ConfigDict(extra="forbid")
    type: str = Field(description="body backend name (see robot_agent.bodies)")


@dataclass(frozen=True)
class Capture:
    """One camera image ``(H, W, 3)`` uint8 RGB, taken at the body's current pose."""

    rgb: np.ndarray
    oracle: OracleCapture | None = None


@runtime_checkable
class RobotBody(Protocol):
    """A mobile base with one camera, driven by the agent's control loop (single thread).

    Poses are odometry estimates (``pose_odom``: base ``(x, y, yaw_rad)`` in the world frame,
    see ``protocol.poses``). ``drive_to`` starts a motion (pre-empting any other) and returns
    ``None``, or the reason the goal is refused; ``step(dt_s)`` advances ``dt_s`` seconds of
    robot time and reports ``moving`` until it returns ``arrived`` or ``failed`` once, then
    ``idle``.
    """

    intrinsics: Intrinsics
    camera_height_m: float
    camera_pitch_deg: float
    max_range_m: float
    oracle: bool

    def pose_odom(self) -> tuple[float, float, float]: ...

    def T_world_cam_odom(self) -> np.ndarray: ...

    def pose_covariance(self) -> np.ndarray | None: ...

    def distance_m(self) -> float: ...

    def viewpoints(self) -> list[Viewpoint]: ...

    def travel_costs_m(self, viewpoints: Sequence[Viewpoint]) -> np.ndarray: ...

    def drive_to(self, x: float, y: float, yaw_rad: float) -> str | None: ...

    def stop(self) -> None: ...

    def step(self, dt_s: float) -> BodyStatus: ...

    def capture(self) -> Capture: ...

    def close(self) -> None: ...
