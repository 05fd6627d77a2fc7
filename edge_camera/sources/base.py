"""The camera source contract: what every backend implements, and the errors it raises."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol, runtime_checkable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from protocol.messages import Intrinsics
from protocol.oracle import OracleCapture


class SourceError(RuntimeError):
    """A transient source fault (device unplugged, stream dropped, file ended, folder empty).

    The node logs it, closes the source, backs off and opens it again; it never exits on one.
    """


class SourceConfigError(ValueError):
    """A source configuration that can never work (the process exits with a clear message)."""


class SourceConfig(BaseModel):
    """Base of every source backend's config; ``type`` picks the backend in the registry."""

    model_config = ConfigDict(extra="forbid")
    type: str = Field(description="source backend name (see the registry in edge_camera.sources)")


@dataclass(frozen=True)
class Grab:
    """One captured image and what the source knows about it.

    ``rgb`` is ``(H, W, 3)`` uint8 RGB; ``stamp_ns`` the capture time (ns since the epoch).
    ``intrinsics`` (at the image's resolution) and ``T_world_cam`` are set when the source knows
    them (a simulated camera, a recording with poses); a calibration file overrides them.
    ``pose_covariance``: ``(6, 6)`` covariance of ``T_world_cam`` (x y z roll pitch yaw; m^2, rad^2) when
    the source declares how accurate its pose is (see :mod:`edge_camera.pose_accuracy`), else None.
    """

    rgb: np.ndarray
    stamp_ns: int
    intrinsics: Intrinsics | None = None
    T_world_cam: np.ndarray | None = None
    pose_trusted: bool = False
    pose_covariance: np.ndarray | None = None
    oracle: OracleCapture | None = None


@runtime_checkable
class FrameSource(Protocol):
    """A camera backend. One object lives for the whole process; ``open``/``close`` may repeat.

    ``read`` returns the next image (blocking at most ``read_timeout_s`` of its config) or raises
    :class:`SourceError`. ``rate_hz`` is the source's own pace (None: as fast as asked);
    ``superseded`` counts frames the source captured but nobody took (live sources keep only the
    newest frame).
    """

    rate_hz: float | None
    superseded: int

    def open(self) -> None: ...

    def read(self) -> Grab: ...

    def close(self) -> None: ...


class SourceBase:
    """Convenience base: no-op ``close``, zero counters. Backends need not inherit it."""

    rate_hz: float | None = None
    superseded: int = 0
    name: ClassVar[str] = ""

    def open(self) -> None:  # pragma: no cover - overridden
        pass

    def close(self) -> None:
        pass
