"""``type = "video"``: a video file, played at its own frame rate (or ``rate_hz``), optionally looping."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Literal

import cv2
from pydantic import Field

from edge_camera.sources.base import Grab, SourceBase, SourceConfig, SourceError


class Config(SourceConfig):
    type: Literal["video"] = Field(default="video", description="video file source")
    path: Path = Field(description="video file (anything OpenCV's FFmpeg reads: mp4, avi, mkv...)")
    loop: bool = Field(default=True, description="start over at the end; false: wait (backing off) at the end")
    rate_hz: float | None = Field(
        default=None, gt=0, description="frames per second to play; default: the file's own frame rate"
    )


class VideoFile(SourceBase):
    def __init__(self, config: Config) -> None:
        self.config = config
        self._cap: Any = None
        self._position = 0  # frames consumed, kept across reopen so a non-looping file is not replayed
        self.rate_hz = config.rate_hz

    def open(self) -> None:
        path = self.config.path
        if not path.is_file():
            raise SourceError(f"video file {path} does not exist")
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"cannot open video file {path}")
        if self.rate_hz is None:
            fps = cap.get(cv2.CAP_PROP_FPS)
            self.rate_hz = float(fps) if fps and 0 < fps <= 1000 else 25.0
        if self._position:
            cap.set(cv2.CAP_PROP_POS_FRAMES, self._position)
        self._cap = cap

    def read(self) -> Grab:
        if self._cap is None:
            raise SourceError("video file not open")
        ok, bgr = self._cap.read()
        if not ok or bgr is None:
            if not self.config.loop:
                raise SourceError(f"end of video file {self.config.path} (loop = false)")
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            self._position = 0
            ok, bgr = self._cap.read()
            if not ok or bgr is None:
                raise SourceError(f"video file {self.config.path} yields no frame")
        self._position += 1
        return Grab(rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), stamp_ns=time.time_ns())

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def create(config: Config) -> VideoFile:
    return VideoFile(config)
