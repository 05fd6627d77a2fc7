"""The I/O shell of ``argus edge-camera``: source -> resize -> JPEG -> Zenoh, with reconnects.

Faults of the source or of the network are transient: logged, counted in the Status, retried
with exponential back-off. Only configuration errors end the process (before anything runs).
"""

from __future__ import annotations

import logging
import threading
import time

from edge_camera.calibration import load_calibration
from edge_camera.config import EdgeCameraConfig
from edge_camera.publish import FramePublisher
from edge_camera.sources import create_source
from edge_camera.sources.base import FrameSource, SourceConfigError
from protocol.keys import Keys
from protocol.messages import OracleFrame
from protocol.node import Node, Process
from protocol.session import Backoff
from protocol.transport import Counters, StatusReporter

log = logging.getLogger("argus.edge_camera")
ROLE = "edge-camera"
STILL_FAILING_LOG_S = 60.0
"""While a source keeps failing, one line says so at most this often (the first failure is logged at once)."""


def quiet_opencv() -> None:
    """Stop OpenCV's own ``[ WARN ]`` lines (one per failed open of a device or stream, on stderr, interleaved with
    Argus's log): the camera's own warning says the same. OpenCV errors still print."""
    import cv2

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


class EdgeCamera(Process):
    """One camera process. ``run(stop)`` blocks until ``stop`` is set; tests call it directly."""

    def __init__(self, config: EdgeCameraConfig) -> None:
        self.config = config
        self.keys = Keys(config.site, config.key_prefix)
        # Configuration errors surface here, before any session is opened.
        self.calibration = load_calibration(config.calibration) if config.calibration else None
        self.source: FrameSource = create_source(config.source)
        self.counters = Counters()
        self.source_open = False
        self._failing_since: float | None = None  # monotonic time of the first failure of the current streak
        self._failures = 0
        self._last_fault_log = 0.0
        self.node = Node(config.zenoh, self.keys, ROLE, config.id, counters=self.counters,
                         status_period_s=config.status_period_s, reconnect=config.reconnect, logger=log)

    def serve(self, node: Node) -> None:
        cid = self.config.id
        node.alive()
        oracle = getattr(self.config.source, "oracle", False)
        publisher = FramePublisher(
            self.config, node.frame_publisher(self.keys.cam_frame(cid)),
            node.publisher(self.keys.oracle("fixed", cid), important=False, message=OracleFrame) if oracle else None,
            self.calibration,
        )
        node.on_exit(self._stopped)
        reporter = node.status(extra=lambda: {
            "frames_dropped": self.counters.get("publish_errors") + getattr(self.source, "superseded", 0)})
        quiet_opencv()
        log.info("edge camera %s: opening its %s source", cid, self.config.source.type)
        self._loop(node.stop, publisher, reporter)

    def _stopped(self) -> None:
        self._close_source()
        log.info("edge camera %s stopped after %d frames", self.config.id, int(self.counters.get("frames_sent")))

    def _close_source(self) -> None:
        if self.source_open:
            self.source_open = False
            try:
                self.source.close()
            except Exception as e:  # noqa: BLE001 - a failing close must not stop the process
                log.warning("closing the source failed: %s", e)

    def _fault(self, reporter: StatusReporter, what: str, backoff: Backoff, stop: threading.Event) -> None:
        wait = backoff.next_wait_s()
        now = time.monotonic()
        self._failures += 1
        if self._failing_since is None:
            self._failing_since, self._last_fault_log = now, now
            log.warning("%s; retrying in %.1f s, then with back-off up to %.0f s until it works (status: degraded)",
                        what, wait, self.config.reconnect.max_s)
        elif now - self._last_fault_log >= STILL_FAILING_LOG_S:
            self._last_fault_log = now
            log.warning("%s; still failing after %d attempts in %.0f s, retrying", what, self._failures,
                        now - self._failing_since)
        reporter.last_error = what
        reporter.state = "degraded"
        self._close_source()
        stop.wait(wait)

    def _loop(self, stop: threading.Event, publisher: FramePublisher, reporter: StatusReporter) -> None:
        backoff = Backoff(self.config.reconnect)
        next_due = time.monotonic()
        opened_once = False
        while not stop.is_set():
            if not self.source_open:
                try:
                    self.source.open()
                except SourceConfigError:
                    raise
                except Exception as e:  # noqa: BLE001 - any open failure is retried (SourceError or not)
                    self.counters.add("reconnect_attempts")
                    self._fault(reporter, f"source open failed: {e}", backoff, stop)
                    continue
                self.source_open = True
                if opened_once:
                    self.counters.add("reconnects")
                    log.info("source reopened")
                else:
                    cid = self.config.id
                    log.info("edge camera %s: source open; publishing on %s", cid, self.keys.cam_frame(cid))
                opened_once = True
                reporter.state = "ok"
            rate = min(self.config.publish.max_rate_hz, getattr(self.source, "rate_hz", None) or float("inf"))
            period = 1.0 / rate
            wait = next_due - time.monotonic()
            if wait > 0:
                stop.wait(wait)
                continue
            # Never burst to catch up after a stall: the schedule restarts from now.
            next_due = max(next_due + period, time.monotonic())
            t0 = time.perf_counter()
            try:
                grab = self.source.read()
            except SourceConfigError:
                raise
            except Exception as e:  # noqa: BLE001 - SourceError, or a backend bug: reopen, never die
                self.counters.add("source_errors")
                self._fault(reporter, f"source failed: {e}", backoff, stop)
                continue
            grab_ms = (time.perf_counter() - t0) * 1e3
            backoff.reset()
            self._failing_since, self._failures = None, 0  # a frame: the fault streak is over
            try:
                done = publisher.publish(grab, grab_ms)
            except Exception as e:  # noqa: BLE001 - a bad frame or a closed link: count it, carry on
                self.counters.add("publish_errors")
                reporter.last_error = f"publish failed: {e}"
                log.warning("publish failed: %s", e)
                continue
            c = self.counters
            if not publisher.delivered():
                c.add("frames_undelivered")  # no subscriber (or no router): not counted as sent
                continue
            c.add("frames_sent")
            c.add("bytes_sent", done.jpeg_bytes)
            c.ema("grab_ms", done.grab_ms)
            c.ema("encode_ms", done.encode_ms)
            c.ema("put_ms", done.put_ms)


def run(config: EdgeCameraConfig, stop: threading.Event | None = None) -> int:
    """Run one edge camera until ``stop`` (default: SIGINT/SIGTERM). Raises on configuration errors."""
    return EdgeCamera(config).run(stop)
