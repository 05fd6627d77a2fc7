"""``type = "opencv"``: a local camera by OpenCV device index (USB webcam, Pi camera via V4L2)."""

from __future__ import annotations

from typing import Any, Literal

import cv2
from pydantic import Field

from edge_camera.sources._live import LiveCapture, LiveSourceBase
from edge_camera.sources.base import SourceConfig

_APIS = {"any": cv2.CAP_ANY, "v4l2": cv2.CAP_V4L2, "gstreamer": cv2.CAP_GSTREAMER, "ffmpeg": cv2.CAP_FFMPEG}


class Config(SourceConfig):
    type: Literal["opencv"] = Field(default="opencv", description="OpenCV device index source")
    device: int = Field(default=0, ge=0, description="device index (/dev/video<N> on Linux)")
    api: Literal["any", "v4l2", "gstreamer", "ffmpeg"] = Field(default="any", description="OpenCV capture API")
    width: int | None = Field(default=None, gt=0, description="resolution to request from the device")
    height: int | None = Field(default=None, gt=0, description="resolution to request from the device")
    fps: float | None = Field(default=None, gt=0, description="frame rate to request from the device")
    fourcc: str | None = Field(
        default=None, min_length=4, max_length=4, description="pixel format to request, e.g. MJPG"
    )
    read_timeout_s: float = Field(default=5.0, gt=0, description="a stall longer than this is a fault")


class OpenCVDevice(LiveSourceBase):
    def __init__(self, config: Config) -> None:
        self.config = config
        self._live = LiveCapture(self._open_capture, f"camera device {config.device}", config.read_timeout_s)

    def _open_capture(self) -> Any:
        c = self.config
        cap = cv2.VideoCapture(c.device, _APIS[c.api])
        if c.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*c.fourcc))
        if c.width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, c.width)
        if c.height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, c.height)
        if c.fps:
            cap.set(cv2.CAP_PROP_FPS, c.fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        return cap


def create(config: Config) -> OpenCVDevice:
    return OpenCVDevice(config)
