"""Grabs into frame samples: resize, JPEG, header (with calibration), ORACLE sample. No threads, no session."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import cv2
import numpy as np

from edge_camera.calibration import Calibration
from edge_camera.config import EdgeCameraConfig, PublishConfig
from edge_camera.sources.base import Grab
from protocol.codec import encode
from protocol.jpeg import encode_jpeg
from protocol.messages import FrameHeader, Intrinsics, rows
from protocol.transport import put_frame

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("argus.edge_camera")


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
        """The header of a frame sent at ``size``: the calibration's intrinsics and pose over the grab's.

        The pose's covariance comes with the pose, from whichever supplied it; no pose, no covariance.
        """
        w, h = size
        intr: Intrinsics | None = grab.intrinsics
        T = grab.T_world_cam
        trusted = grab.pose_trusted
        cov = grab.pose_covariance
        if self.calibration is not None:
            if self.calibration.intrinsics is not None:
                intr = self.calibration.intrinsics
            if self.calibration.T_world_cam is not None:
                # The grab's covariance describes the grab's pose, not this one.
                T, trusted, cov = self.calibration.T_world_cam, True, self.calibration.pose_covariance
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
            pose_covariance=None if T is None or cov is None else rows(cov),
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
            oracle = grab.oracle.message(self.config.id, self.seq, grab.stamp_ns, lambda im: _resize_nearest(im, size))
            # The ORACLE sample goes first, so a consumer holding a frame can already match it.
            self.oracle_pub.put(encode(oracle))
        put_frame(self.frame_pub, header, jpeg)
        t2 = time.perf_counter()
        self.seq += 1
        return Published(grab_ms, (t1 - t0) * 1e3, (t2 - t1) * 1e3, len(jpeg))
