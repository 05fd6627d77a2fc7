"""Recorded RGB-D sequences in the shared layout, and their frames fed the way the wire feeds them.

A sequence is a folder::

    frames/frame-NNNNNN.color.png     RGB (any image OpenCV reads; .jpg too)
    frames/frame-NNNNNN.depth.png     uint16 depth, metres = (value >> depth_shift) / depth_divisor, 0 = none
    frames/frame-NNNNNN.pose.txt      4x4 T_world_cam (camera to world, metres, OpenCV camera axes)
    camera-intrinsics.txt             the 3x3 K in its first three rows
    meta.json                         what the folder's README says, as data (:class:`SequenceMeta`)

The frames, poses and K are read with the edge camera's ``recorded`` source's readers
(``edge_camera.sources.recorded``), so the bench and a replayed camera play the same frames.
Sequences of ``../shared/data`` packaged before ``meta.json`` existed are described by a file of the same
fields in ``bench/sequence_meta/<folder name>.json``; a folder with neither is refused with one line naming
the missing file.

:func:`wire_views` turns recorded frames into mapper views the way a live camera's frames become views: a
``FrameHeader`` (intrinsics, pose, and the pose covariance when an accuracy is declared) plus the JPEG the
edge camera would send, decoded by the mapper's own intake (``mapper.inbox.FrameIntake``). Nothing a live
frame cannot carry reaches the reconstructor.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from edge_camera.sources.base import SourceConfigError
from edge_camera.sources.recorded import list_color_images, read_intrinsics_matrix, read_pose, world_transform
from mapper.geometry.contract import View
from protocol.messages import FrameHeader, Intrinsics
from protocol.poses import PoseAccuracy, covariance_from_accuracy

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_ROOT = REPO_ROOT / ".." / "shared" / "data"
SIDECAR_DIR = Path(__file__).resolve().parent / "sequence_meta"
JPEG_QUALITY = 85
"""The edge camera's default ``publish.jpeg_quality``: recorded frames are compressed as a camera sends them."""


class SequenceError(ValueError):
    """A sequence folder that cannot be read; the message is one line naming the file."""


class SequenceMeta(BaseModel):
    """``meta.json`` of a sequence folder (fields not listed here are kept in the README only and ignored)."""

    model_config = ConfigDict(extra="ignore")
    depth_divisor: float = Field(gt=0, description="recorded depth in metres = (value >> depth_shift) / depth_divisor")
    depth_shift: int = Field(default=0, ge=0, le=15, description="bits the raw depth value is shifted right first")
    valid_depth_m: tuple[float, float] = Field(description="recorded depth is scored only inside this range, metres")
    intrinsics_file: str = Field(default="camera-intrinsics.txt", description="the file holding K (first 3 rows)")
    pose_sigma_trans_m: float | None = Field(
        default=None, gt=0, description="stated accuracy of the recorded poses: position std-dev, metres"
    )
    pose_sigma_rot_deg: float | None = Field(
        default=None, gt=0, description="stated accuracy of the recorded poses: rotation std-dev, degrees"
    )
    world_from_recording: list[list[float]] | None = Field(
        default=None,
        description="rigid 4x4 taking the recording's world frame to Argus's (z up, floor at z = 0); every pose is "
        "read as world_from_recording @ T_world_cam, as the edge camera's recorded source sends it",
    )
    licence: str = Field(default="", description="the data's licence")
    pose_source: str = Field(default="", description="where the poses come from")

    @model_validator(mode="after")
    def _both_or_neither(self) -> SequenceMeta:
        if (self.pose_sigma_trans_m is None) != (self.pose_sigma_rot_deg is None):
            raise ValueError("pose_sigma_trans_m and pose_sigma_rot_deg go together (both or neither)")
        world_transform(self.world_from_recording, "meta")  # raises ValueError (PoseError) when not rigid
        return self

    def declared(self) -> PoseAccuracy | None:
        """The accuracy the sequence states for its poses, when it states both parts."""
        if self.pose_sigma_trans_m is None or self.pose_sigma_rot_deg is None:
            return None
        return PoseAccuracy(self.pose_sigma_trans_m, self.pose_sigma_rot_deg)


@dataclass
class RecordedFrame:
    """One recorded frame: RGB, its recorded pose (the prior and the reference), recorded depth in metres."""

    index: int
    rgb: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    depth_m: np.ndarray
    valid: np.ndarray


@dataclass
class Sequence:
    name: str
    folder: Path
    meta: SequenceMeta
    frames: list[RecordedFrame]
    poses_projected: int


def meta_path(folder: Path) -> Path | None:
    """The folder's ``meta.json``, else its sidecar in ``bench/sequence_meta``, else None."""
    own = folder / "meta.json"
    if own.is_file():
        return own
    side = SIDECAR_DIR / f"{folder.resolve().name}.json"
    return side if side.is_file() else None


def discover(root: Path = DATA_ROOT) -> list[Path]:
    """Every sequence folder under ``root`` that has a ``frames/`` folder and a meta file, sorted by name."""
    if not root.is_dir():
        return []
    return sorted(d for d in root.iterdir() if (d / "frames").is_dir() and meta_path(d) is not None)


def read_meta(folder: Path) -> SequenceMeta:
    path = meta_path(folder)
    if path is None:
        raise SequenceError(f"{folder / 'meta.json'}: missing (it says how to read the depth: depth_divisor, "
                            "valid_depth_m)")
    try:
        return SequenceMeta.model_validate(json.loads(path.read_text()))
    except (OSError, json.JSONDecodeError) as e:
        raise SequenceError(f"{path}: unreadable: {e}") from None
    except ValidationError as e:
        first = e.errors()[0]
        raise SequenceError(f"{path}: {'.'.join(str(p) for p in first['loc'])}: {first['msg']}") from None


def _image(path: Path, flags: int) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    if img is None:
        raise SequenceError(f"{path}: missing or not an image")
    return np.asarray(img)


def load(folder: Path, start: int = 0, stop: int | None = None) -> Sequence:
    """Read a sequence folder (frames ``start`` .. ``stop`` - 1 of the sorted list). Raises
    :class:`SequenceError` with one line naming the file for a missing or bad file."""
    folder = Path(folder)
    meta = read_meta(folder)
    kpath = folder / meta.intrinsics_file
    try:  # the layout is read as the edge camera's recorded source reads it, so both play the same frames
        K = read_intrinsics_matrix(kpath)
    except SourceConfigError as e:
        raise SequenceError(f"{kpath}: missing or not a 3x3 matrix: {e}") from None
    frames_dir = folder / "frames"
    colours = list_color_images(frames_dir) if frames_dir.is_dir() else []
    if not colours:
        raise SequenceError(f"{frames_dir}: no frame-NNNNNN.color.* images")
    frames, projected = [], 0
    lo, hi = meta.valid_depth_m
    W = world_transform(meta.world_from_recording, "meta")
    for i, p in enumerate(colours[start:stop], start=start):
        stem = p.name.split(".color.")[0]
        pose_file = p.parent / f"{stem}.pose.txt"
        if not pose_file.is_file():
            raise SequenceError(f"{pose_file}: missing")
        try:
            chk = read_pose(pose_file)
        except ValueError as e:  # PoseError included
            raise SequenceError(f"{pose_file}: not a 4x4 pose: {e}") from None
        projected += int(chk.projected)
        bgr = _image(p, cv2.IMREAD_COLOR)
        dpath = p.parent / f"{stem}.depth.png"
        raw = _image(dpath, cv2.IMREAD_UNCHANGED)
        if raw.ndim != 2 or raw.shape != bgr.shape[:2] or raw.dtype != np.uint16:
            raise SequenceError(f"{dpath}: expected {bgr.shape[1]}x{bgr.shape[0]} uint16 depth, got "
                                f"{raw.shape} {raw.dtype}")
        depth = (raw >> meta.depth_shift).astype(np.float32) / np.float32(meta.depth_divisor)
        rgb = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), dtype=np.uint8)
        T = chk.T if W is None else W @ chk.T
        frames.append(RecordedFrame(i, rgb, K, T, depth, (depth > lo) & (depth < hi)))
    return Sequence(folder.resolve().name, folder, meta, frames, projected)


def header_for(frame: RecordedFrame, source_id: str, seq: int, stamp_ns: int,
               declared: PoseAccuracy | None) -> FrameHeader:
    """The header a camera playing this recording sends: intrinsics, the recorded pose as a prior (not
    trusted) and, when an accuracy is declared, the matching pose covariance."""
    h, w = frame.rgb.shape[:2]
    K = frame.K
    cov = None if declared is None else covariance_from_accuracy(declared.trans_m, declared.rot_deg).tolist()
    return FrameHeader(
        source_id=source_id, source_kind="fixed", seq=seq, stamp_ns=stamp_ns, width=w, height=h,
        intrinsics=Intrinsics(width=w, height=h, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2]),
        T_world_cam=frame.T_world_cam.tolist(), pose_covariance=cov, pose_trusted=False,
    )


class WireFeed:
    """Recorded frames through the mapper's intake, one at a time, exactly as frames from the wire arrive:
    header + JPEG encoded, the sample's bytes decoded (``protocol.transport.decode_frame_bytes``), checked
    (``FrameIntake.admit_frame``), taken from the ring, JPEG-decoded and made a view (``FrameIntake.view``).
    The intake keeps its per-source state (the declared accuracy's floor) across frames, like a live mapper."""

    def __init__(self, source_id: str = "replay", jpeg_quality: int = JPEG_QUALITY) -> None:
        from mapper.config import MapperConfig
        from mapper.inbox import FrameIntake
        from protocol.keys import Keys
        from protocol.ratelog import RateLimitedLog
        from protocol.transport import Counters

        self.source_id, self.jpeg_quality = source_id, jpeg_quality
        self.config = MapperConfig()
        self.keys = Keys(site=self.config.site)
        self.counters = Counters()
        self.intake = FrameIntake(self.config, self.keys, self.counters,
                                  RateLimitedLog(logging.getLogger("bench.sequences")))
        self.seq = 0

    def view(self, frame: RecordedFrame, declared: PoseAccuracy | None, stamp_ns: int | None = None) -> View | None:
        """The view the mapper makes of ``frame`` (None when its intake refused it; see ``counters``)."""
        from protocol.codec import encode
        from protocol.jpeg import encode_jpeg
        from protocol.transport import decode_frame_bytes

        seq = self.seq
        self.seq += 1
        header = header_for(frame, self.source_id, seq, (seq + 1) * 33_333_333 if stamp_ns is None else stamp_ns,
                            declared)
        key = self.keys.frame("fixed", self.source_id)
        self.intake.admit_frame(decode_frame_bytes(key, encode(header), encode_jpeg(frame.rgb, self.jpeg_quality)))
        out = None
        for f, oracle in self.intake.ready(0.0):
            rgb = self.intake.decode(f)
            if rgb is None:
                continue
            try:
                out = self.intake.view(f, rgb, oracle)
            finally:
                self.intake.release(f)
        return out


def wire_views(frames: list[RecordedFrame], declared: PoseAccuracy | None,
               source_id: str = "replay", rate_hz: float = 30.0) -> list[View]:
    """Every frame's view through one :class:`WireFeed` (frames the intake refuses are left out), stamped as if
    captured at ``rate_hz`` (the keyframe selection reads time: a frame over ``keyframes.refresh_s`` after the
    last keyframe is reconsidered)."""
    feed = WireFeed(source_id)
    step_ns = round(1e9 / rate_hz)
    views = [feed.view(f, declared, stamp_ns=(k + 1) * step_ns) for k, f in enumerate(frames)]
    return [v for v in views if v is not None]
