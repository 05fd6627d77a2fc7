"""``type = "stream"``: a network stream by URL (RTSP, HTTP MJPEG, anything OpenCV's FFmpeg opens)."""

from __future__ import annotations

from typing import Any, Literal

import cv2
from pydantic import Field, field_validator

from edge_camera.sources._live import LiveCapture, LiveSourceBase
from edge_camera.sources.base import SourceConfig


class Config(SourceConfig):
    type: Literal["stream"] = Field(default="stream", description="RTSP/HTTP stream source")
    url: str = Field(description="stream URL, e.g. rtsp://10.0.0.5:554/stream1 or http://host/mjpg")
    open_timeout_s: float = Field(default=10.0, gt=0, description="give up opening the stream after this")
    read_timeout_s: float = Field(default=5.0, gt=0, description="a stall longer than this is a fault")

    @field_validator("url")
    @classmethod
    def _scheme(cls, v: str) -> str:
        if "://" not in v:
            raise ValueError("url needs a scheme such as rtsp:// or http://")
        return v


class Stream(LiveSourceBase):
    def __init__(self, config: Config) -> None:
        self.config = config
        self._live = LiveCapture(self._open_capture, f"stream {self._redacted()}", config.read_timeout_s)

    def _redacted(self) -> str:
        # Never log credentials embedded in the URL (rtsp://user:pass@host/...).
        scheme, _, rest = self.config.url.partition("://")
        host = rest.split("@", 1)[-1]
        return f"{scheme}://{host}"

    def _open_capture(self) -> Any:
        c = self.config
        ms = int(c.open_timeout_s * 1000)
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(c.read_timeout_s * 1000)]
        return cv2.VideoCapture(c.url, cv2.CAP_FFMPEG, params)


def create(config: Config) -> Stream:
    return Stream(config)
