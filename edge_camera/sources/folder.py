"""``type = "folder"``: the images of a folder in sorted name order, at a given rate.

The folder is listed again at each pass, so images added later are picked up. An empty or missing
folder, or an image that vanished before it was read, is a transient fault (back off, list again); a
corrupt image is skipped and counted.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Literal

import cv2
from pydantic import Field

from edge_camera.sources.base import Grab, SourceBase, SourceConfig, SourceError

log = logging.getLogger(__name__)


class Config(SourceConfig):
    type: Literal["folder"] = Field(default="folder", description="image folder source")
    path: Path = Field(description="folder holding the images")
    extensions: list[str] = Field(
        default=[".jpg", ".jpeg", ".png", ".bmp"], description="file name endings taken (case-insensitive)"
    )
    rate_hz: float = Field(default=2.0, gt=0, description="images per second")
    loop: bool = Field(default=True, description="start over after the last image; false: wait for new ones")


class ImageFolder(SourceBase):
    def __init__(self, config: Config) -> None:
        self.config = config
        self.rate_hz = config.rate_hz
        self._files: list[Path] = []
        self._index = 0
        self._last_name: str | None = None
        self.skipped = 0

    def _list(self) -> list[Path]:
        d = self.config.path
        if not d.is_dir():
            raise SourceError(f"image folder {d} does not exist")
        ends = tuple(e.lower() for e in self.config.extensions)
        files = sorted(p for p in d.iterdir() if p.name.lower().endswith(ends) and p.is_file())
        if not files:
            raise SourceError(f"image folder {d} holds no images")
        return files

    def open(self) -> None:
        self._files = self._list()
        # Resume after the last image sent (by name), so a reconnect does not replay the folder.
        self._index = 0
        if self._last_name is not None:
            self._index = next((i for i, p in enumerate(self._files) if p.name > self._last_name), len(self._files))

    def read(self) -> Grab:
        for _ in range(len(self._files) + 1):
            if self._index >= len(self._files):
                self._files = self._list()
                if self.config.loop:
                    self._index = 0
                else:
                    self.open()
                    if self._index >= len(self._files):
                        raise SourceError(f"no new images in {self.config.path} (loop = false)")
            path = self._files[self._index]
            self._index += 1
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is None:
                if not path.exists():
                    raise SourceError(f"image {path} vanished")
                self.skipped += 1
                log.warning("skipping unreadable image %s", path)
                continue
            self._last_name = path.name
            return Grab(rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), stamp_ns=time.time_ns())
        raise SourceError(f"no readable image in {self.config.path}")


def create(config: Config) -> ImageFolder:
    return ImageFolder(config)
