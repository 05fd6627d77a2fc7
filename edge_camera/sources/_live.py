"""A live OpenCV capture read by a background thread that keeps only the newest frame.

Devices and network streams deliver frames at their own pace and buffer when nobody reads; reading
them continuously and handing out only the newest keeps latency low at any publish rate.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from edge_camera.sources.base import Grab, SourceBase, SourceError

log = logging.getLogger(__name__)


class LiveCapture:
    """Owns a ``cv2.VideoCapture`` made by ``opener``; ``latest`` waits for a frame newer than the last."""

    def __init__(self, opener: Callable[[], Any], what: str, read_timeout_s: float) -> None:
        self._opener = opener
        self.what = what
        self.read_timeout_s = read_timeout_s
        self._cap: Any = None
        self._cond = threading.Condition()
        self._frame: np.ndarray | None = None
        self._stamp_ns = 0
        self._count = 0
        self._taken = 0
        self._error: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.superseded = 0

    def open(self) -> None:
        cap = self._opener()
        if cap is None or not cap.isOpened():
            if cap is not None:
                cap.release()
            raise SourceError(f"cannot open {self.what}")
        self._cap = cap
        self._stop.clear()
        with self._cond:
            self._frame, self._error, self._count, self._taken = None, None, 0, 0
        self._thread = threading.Thread(target=self._run, name="live-capture", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        cap = self._cap
        try:
            while not self._stop.is_set():
                ok, bgr = cap.read()
                stamp = time.time_ns()
                with self._cond:
                    if not ok or bgr is None:
                        self._error = f"{self.what}: no frame (device unplugged or stream ended)"
                        self._cond.notify_all()
                        return
                    if self._count > self._taken:
                        self.superseded += 1
                    self._frame, self._stamp_ns = bgr, stamp
                    self._count += 1
                    self._cond.notify_all()
        finally:
            # Released by the reading thread itself: releasing under a blocked read() is unsafe.
            cap.release()

    def latest(self) -> Grab:
        deadline = time.monotonic() + self.read_timeout_s
        with self._cond:
            while self._count <= self._taken and self._error is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise SourceError(f"{self.what}: no frame for {self.read_timeout_s:g} s (stalled)")
                self._cond.wait(left)
            if self._count <= self._taken:
                raise SourceError(self._error or f"{self.what}: failed")
            self._taken = self._count
            bgr, stamp = self._frame, self._stamp_ns
        assert bgr is not None
        if bgr.ndim == 2:
            rgb = cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB)
        else:
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        return Grab(rgb=rgb, stamp_ns=stamp)

    def close(self) -> None:
        self._stop.set()
        self._cap = None
        if self._thread is not None:
            # cap.read() may block on a dead stream; the thread is a daemon, do not wait forever.
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                log.warning("%s: capture thread still blocked; abandoning it", self.what)
            self._thread = None


class LiveSourceBase(SourceBase):
    """A source backed by a :class:`LiveCapture` reader thread (devices and network streams):
    subclasses set ``self._live`` in ``__init__``; reads return the newest frame."""

    _live: LiveCapture

    @property
    def superseded(self) -> int:  # type: ignore[override]
        return self._live.superseded

    def open(self) -> None:
        self._live.open()

    def read(self) -> Grab:
        return self._live.latest()

    def close(self) -> None:
        self._live.close()
