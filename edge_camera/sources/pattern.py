"""``type = "pattern"``: a synthetic moving test pattern (smoke tests, benchmarks, link checks)."""

from __future__ import annotations

import time
from typing import Literal

import numpy as np
from pydantic import Field

from edge_camera.sources.base import Grab, SourceBase, SourceConfig


class Config(SourceConfig):
    type: Literal["pattern"] = Field(default="pattern", description="synthetic test pattern source")
    width: int = Field(default=640, gt=0, le=8192, description="image width, pixels")
    height: int = Field(default=480, gt=0, le=8192, description="image height, pixels")
    rate_hz: float | None = Field(default=10.0, gt=0, description="frames per second (none: as fast as asked)")


class Pattern(SourceBase):
    """Colour gradients with textured noise that scroll by a few pixels per frame (JPEG-realistic)."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.rate_hz = config.rate_hz
        h, w = config.height, config.width
        rng = np.random.default_rng(0)
        yy, xx = np.mgrid[0:h, 0:w]
        base = np.stack([xx * 255 // max(w - 1, 1), yy * 255 // max(h - 1, 1), (xx + yy) % 256], axis=-1)
        noise = rng.integers(0, 48, size=(h, w, 1))
        self._base = np.clip(base + noise, 0, 255).astype(np.uint8)
        self._n = 0

    def open(self) -> None:
        pass

    def read(self) -> Grab:
        self._n += 1
        rgb = np.roll(self._base, shift=(self._n * 3) % self.config.width, axis=1)
        return Grab(rgb=rgb, stamp_ns=time.time_ns())


def create(config: Config) -> Pattern:
    return Pattern(config)
