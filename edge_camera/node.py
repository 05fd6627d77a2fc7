"""The I/O shell of ``argus edge-camera``: source -> resize -> JPEG -> Zenoh, with reconnects.

Faults of the source or of the network are transient: logged, counted in the Status, retried
with exponential back-off. Only configuration errors end the process (before anything runs).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import cv2
import numpy as np

from edge_camera.calibration import Calibration, load_calibration
from edge_camera.config import EdgeCameraConfig, PublishConfig, ReconnectConfig
from edge_camera.sources import create_source
from edge_camera.sources.base import FrameSource, Grab, SourceConfigError
from protocol.codec import encode
from protocol.jpeg import encode_jpeg
from protocol.keys import Keys
from protocol.messages import FrameHeader, Intrinsics, OracleFrame, rows
from protocol.oracle import depth_to_png, ids_to_png
from protocol.session import open_session_retrying
from protocol.transport import Counters, StatusReporter, declare_frame_publisher, declare_message_publisher, put_frame

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("argus.edge_camera")
ROLE = "edge-camera"


class Backoff:
    """Exponential back-off: ``initial_s``, then times ``factor`` per failure, capped at ``max_s``."""

    def __init__(self, config: ReconnectConfig) -> None:
        self.config = config
        self.failures = 0

    def next_wait_s(self) -> float:
        c = self.config
        wait = min(c.max_s, c.initial_s * c.factor**self.failures)
        self.failures += 1
        return wait

    def reset(self) -> None:
        self.failures = 0


def output_size(width: int, height: int, publish: PublishConfig) -> tuple[int, int]:
    """``(width, height)`` frames are sent at, from the source size and the publish settings."""
    if publish.width and publish.height:
        return publish.width, publish.height
    if publish.width:
        return publish.width, max(1, round(height * publish.width / width))
    if publish.height:
        return max(1, round(width * publish.height / height)), publish.height
    return width, height


def resize_rgb(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if (rgb.shape[1], rgb.shape[0]) == size:
        return rgb
    shrink = size[0] < rgb.shape[1]
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def _resize_nearest(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if (image.shape[1], image.shape[0]) == size:
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_NEAREST)


@dataclass
class Published:
    """Timings of one published frame, milliseconds."""

    grab_ms: float
    encode_ms: float
    put_ms: float
    jpeg_bytes: int


class FramePublisher:
    """Turns grabs into frame samples (and ORACLE samples) on one camera's keys. No threads."""

    def __init__(
        self,
        config: EdgeCameraConfig,
        frame_pub: zenoh.Publisher,
        oracle_pub: zenoh.Publisher | None,
        calibration: Calibration | None,
    ) -> None:
        self.config = config
        self.frame_pub = frame_pub
        self.oracle_pub = oracle_pub
        self.calibration = calibration
        self.seq = 0
        self._warned_aspect = False

    def header_for(self, grab: Grab, size: tuple[int, int]) -> FrameHeader:
        w, h = size
        intr: Intrinsics | None = grab.intrinsics
        T = grab.T_world_cam
        trusted = grab.pose_trusted
        if self.calibration is not None:
            if self.calibration.intrinsics is not None:
                intr = self.calibration.intrinsics
            if self.calibration.T_world_cam is not None:
                T, trusted = self.calibration.T_world_cam, True
        if intr is not None and (intr.width, intr.height) != (w, h):
            if not self._warned_aspect and abs(intr.width / intr.height - w / h) > 0.01:
                log.warning("calibration is for %dx%d but frames are %dx%d (aspect differs); scaling anyway",
                            intr.width, intr.height, w, h)
                self._warned_aspect = True
            intr = intr.scaled(w, h)
        return FrameHeader(
            source_id=self.config.id,
            source_kind="fixed",
            seq=self.seq,
            stamp_ns=grab.stamp_ns,
            width=w,
            height=h,
            intrinsics=intr,
            T_world_cam=None if T is None else rows(T),
            pose_trusted=trusted if T is not None else False,
        )

    def delivered(self) -> bool:
        """Whether anyone (through a router) subscribes to the frame key right now: a frame put with no
        subscriber goes nowhere and is not counted as sent."""
        try:
            # zenoh 1.10 returns a MatchingStatus here; its stub says bool
            return cast("zenoh.MatchingStatus", self.frame_pub.matching_status).matching
        except Exception:  # noqa: BLE001 - a publisher without matching support: assume delivered
            return True

    def publish(self, grab: Grab, grab_ms: float = 0.0) -> Published:
        t0 = time.perf_counter()
        h0, w0 = grab.rgb.shape[:2]
        size = output_size(w0, h0, self.config.publish)
        rgb = resize_rgb(grab.rgb, size)
        jpeg = encode_jpeg(rgb, self.config.publish.jpeg_quality)
        header = self.header_for(grab, size)
        t1 = time.perf_counter()
        if grab.oracle is not None and self.oracle_pub is not None:
            o = grab.oracle
            oracle = OracleFrame(
                source_id=self.config.id,
                seq=self.seq,
                stamp_ns=grab.stamp_ns,
                T_world_cam_true=rows(o.T_world_cam_true),
                ids_png=ids_to_png(_resize_nearest(o.instance_id, size)),
                depth_png=depth_to_png(_resize_nearest(o.depth_m, size)),
                labels={str(k): v for k, v in o.labels.items()},
            )
            # The ORACLE sample goes first, so a consumer holding a frame can already match it.
            self.oracle_pub.put(encode(oracle))
        put_frame(self.frame_pub, header, jpeg)
        t2 = time.perf_counter()
        self.seq += 1
        return Published(grab_ms, (t1 - t0) * 1e3, (t2 - t1) * 1e3, len(jpeg))


def _ema(counters: Counters, name: str, value: float, alpha: float = 0.2) -> None:
    old = counters.get(name)
    counters.set(name, value if old == 0.0 else (1 - alpha) * old + alpha * value)


class EdgeCamera:
    """One camera process. ``run(stop)`` blocks until ``stop`` is set; tests call it directly."""

    def __init__(self, config: EdgeCameraConfig) -> None:
        self.config = config
        self.keys = Keys(config.site, config.key_prefix)
        # Configuration errors surface here, before any session is opened.
        self.calibration = load_calibration(config.calibration) if config.calibration else None
        self.source: FrameSource = create_source(config.source)
        self.counters = Counters()
        self.source_open = False

    def _open_session(self, stop: threading.Event) -> zenoh.Session | None:
        backoff = Backoff(self.config.reconnect)

        def next_wait_s() -> float:
            self.counters.add("session_attempts")
            return backoff.next_wait_s()

        return open_session_retrying(self.config.zenoh, stop, log, next_wait_s)

    def run(self, stop: threading.Event) -> int:
        session = self._open_session(stop)
        if session is None:
            return 0
        with session:
            cid = self.config.id
            token = session.liveliness().declare_token(self.keys.alive(ROLE, cid))
            frame_pub = declare_frame_publisher(session, self.keys.cam_frame(cid))
            oracle_pub = (
                declare_message_publisher(session, self.keys.oracle("fixed", cid), important=False, message=OracleFrame)
                if getattr(self.config.source, "oracle", False)
                else None
            )
            publisher = FramePublisher(self.config, frame_pub, oracle_pub, self.calibration)
            reporter = StatusReporter(
                session,
                self.keys.status(ROLE, cid),
                ROLE,
                cid,
                self.counters,
                self.config.status_period_s,
                extra=lambda: {
                    "frames_dropped": self.counters.get("publish_errors") + getattr(self.source, "superseded", 0)
                },
            )
            log.info("edge camera %s publishing on %s", cid, self.keys.cam_frame(cid))
            try:
                with reporter:
                    self._loop(stop, publisher, reporter)
            finally:
                self._close_source()
                token.undeclare()
                log.info("edge camera %s stopped after %d frames", cid, int(self.counters.get("frames_sent")))
        return 0

    def _close_source(self) -> None:
        if self.source_open:
            self.source_open = False
            try:
                self.source.close()
            except Exception as e:  # noqa: BLE001 - a failing close must not stop the process
                log.warning("closing the source failed: %s", e)

    def _fault(self, reporter: StatusReporter, what: str, backoff: Backoff, stop: threading.Event) -> None:
        wait = backoff.next_wait_s()
        log.warning("%s; retrying in %.1f s", what, wait)
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
            _ema(c, "grab_ms", done.grab_ms)
            _ema(c, "encode_ms", done.encode_ms)
            _ema(c, "put_ms", done.put_ms)


def run(config: EdgeCameraConfig, stop: threading.Event | None = None) -> int:
    """Run one edge camera until ``stop`` (default: SIGINT/SIGTERM). Raises on configuration errors."""
    from protocol.runtime import install_stop_handlers

    camera = EdgeCamera(config)
    stop_event = stop if stop is not None else install_stop_handlers()
    return camera.run(stop_event)
