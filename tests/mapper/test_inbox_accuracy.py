"""A frame's declared pose accuracy reaches the reconstructor through the mapper's own intake."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from mapper.config import MapperConfig
from mapper.inbox import FrameIntake, PriorAccuracy
from protocol.codec import encode
from protocol.jpeg import encode_jpeg
from protocol.keys import Keys
from protocol.messages import FrameHeader, Intrinsics
from protocol.poses import covariance_from_accuracy, look_at
from protocol.ratelog import RateLimitedLog
from protocol.transport import Counters, decode_frame_bytes

W, H = 64, 48


def _intake() -> FrameIntake:
    cfg = MapperConfig()
    return FrameIntake(cfg, Keys(site=cfg.site), Counters(), RateLimitedLog(logging.getLogger("test")))


def _through(intake: FrameIntake, seq: int, cov: np.ndarray | None, pose: bool = True, source: str = "cam1",
             map_always: bool = False):
    """One frame sample's bytes through the intake as the mapper's subscriber hands it on; returns the view."""
    rng = np.random.default_rng(seq)
    rgb = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    hdr = FrameHeader(source_id=source, source_kind="fixed", seq=seq, stamp_ns=seq + 1, width=W, height=H,
                      intrinsics=Intrinsics.from_fov(W, H, 60.0),
                      T_world_cam=look_at([0.1 * seq, 0, 1], [0.1 * seq, 2, 1]).tolist() if pose else None,
                      pose_covariance=None if cov is None else cov.tolist(), map_always=map_always)
    intake.admit_frame(decode_frame_bytes(intake.keys.frame("fixed", source), encode(hdr), encode_jpeg(rgb, 90)))
    views = []
    for f, oracle in intake.ready(0.0):
        img = intake.decode(f)
        assert img is not None
        views.append(intake.view(f, img, oracle))
        intake.release(f)
    assert len(views) == 1
    return views[0]


def test_declared_covariance_reaches_the_view_as_an_accurate_prior() -> None:
    intake = _intake()
    cov = covariance_from_accuracy(0.002, 0.05)
    v = _through(intake, 0, cov)
    assert v.prior_rel_rot_deg == pytest.approx(0.05)
    assert v.prior_rel_trans_m == pytest.approx(0.002)
    assert v.pose_covariance is not None and np.allclose(v.pose_covariance, cov)


def test_no_covariance_reaches_the_view_as_undeclared() -> None:
    v = _through(_intake(), 0, None)
    assert v.prior_rel_rot_deg is None and v.prior_rel_trans_m is None and v.pose_covariance is None


def test_a_covariance_without_a_pose_declares_nothing() -> None:
    v = _through(_intake(), 0, covariance_from_accuracy(0.002, 0.05), pose=False)
    assert v.T_world_cam is None and v.prior_rel_rot_deg is None


def test_a_negative_variance_is_counted_and_the_frame_goes_on_undeclared() -> None:
    intake = _intake()
    cov = covariance_from_accuracy(0.002, 0.05)
    cov[4, 4] = -1e-4
    v = _through(intake, 0, cov)
    assert v is not None and v.prior_rel_rot_deg is None
    assert intake.counters.get("frames_bad_covariance") == 1


def test_growing_covariance_is_drift_on_top_of_the_smallest_declared() -> None:
    acc = PriorAccuracy(max_sources=2)
    first = acc.fields("robot", covariance_from_accuracy(0.001, 0.05))
    later = acc.fields("robot", covariance_from_accuracy(0.05, 2.0))  # odometry after a long drive
    # The per-frame part stays the smallest declared; the drift is in the covariance (mvs reads its growth).
    assert first["prior_rel_rot_deg"] == pytest.approx(0.05) and later["prior_rel_rot_deg"] == pytest.approx(0.05)
    assert later["prior_rel_trans_m"] == pytest.approx(0.001)
    acc.fields("a", covariance_from_accuracy(0.1, 1.0))
    acc.fields("b", covariance_from_accuracy(0.1, 1.0))  # bounded: "robot" (the oldest) is forgotten
    again = acc.fields("robot", covariance_from_accuracy(0.05, 2.0))
    assert again["prior_rel_rot_deg"] == pytest.approx(2.0)


def test_drift_between_two_views_widens_their_between_factor() -> None:
    from mapper.geometry.contract import View
    from mapper.geometry.mvs import _drift_variance

    img = np.zeros((H, W, 3), np.uint8)
    a = View(img, "r", pose_covariance=covariance_from_accuracy(0.01, 0.1))
    b = View(img, "r", pose_covariance=covariance_from_accuracy(0.02, 0.3))
    assert _drift_variance(a, b, slice(3, 6)) == pytest.approx(np.radians(0.3) ** 2 - np.radians(0.1) ** 2)
    assert _drift_variance(a, b, slice(0, 3)) == pytest.approx(0.02**2 - 0.01**2)
    assert _drift_variance(a, View(img, "r"), slice(0, 3)) == 0.0


def test_oracle_images_of_another_size_than_their_frame_are_refused_unread() -> None:
    """A small PNG claiming 6000x6000 (or any size but the frame's) is refused from its header; the frame is
    counted and dropped, and a matching one still goes through."""
    import struct
    import zlib

    from protocol.messages import OracleFrame
    from protocol.oracle import depth_to_png

    def claiming(w: int, h: int) -> bytes:  # a valid PNG header claiming w x h, 16-bit grey, and no real data
        ihdr = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)
        chunk = b"IHDR" + ihdr
        return (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + chunk
                + struct.pack(">I", zlib.crc32(chunk) & 0xFFFFFFFF) + b"\x00" * 64)

    intake = _intake()
    rgb = np.zeros((H, W, 3), np.uint8)
    hdr = FrameHeader(source_id="cam1", source_kind="fixed", seq=0, stamp_ns=1, width=W, height=H)
    frame = decode_frame_bytes(intake.keys.frame("fixed", "cam1"), encode(hdr), encode_jpeg(rgb, 90))
    pose = np.eye(4).tolist()
    bomb = OracleFrame(source_id="cam1", seq=0, stamp_ns=1, T_world_cam_true=pose, depth_png=claiming(6000, 6000))
    assert intake.view(frame, rgb, bomb) is None
    assert intake.counters.get("decode_errors") == 1
    good = OracleFrame(source_id="cam1", seq=0, stamp_ns=1, T_world_cam_true=pose,
                       depth_png=depth_to_png(np.ones((H, W), np.float32)))
    v = intake.view(frame, rgb, good)
    assert v is not None and v.oracle is not None and v.oracle.depth_m.shape == (H, W)
    half = OracleFrame(source_id="cam1", seq=0, stamp_ns=1, T_world_cam_true=pose,
                       depth_png=depth_to_png(np.ones((H // 2, W // 2), np.float32)))
    assert intake.view(frame, rgb, half) is None and intake.counters.get("decode_errors") == 2


def test_a_frame_its_sender_needs_mapped_says_so_in_its_view() -> None:
    intake = _intake()
    assert _through(intake, 0, None).map_always is False
    assert _through(intake, 1, None, map_always=True).map_always is True  # a robot's arrival view (schema 1.1)
