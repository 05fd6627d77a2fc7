"""``type = "recorded"``: a recorded RGB sequence with a camera pose per frame, played at a given rate.

Example::

    argus edge-camera --config edge_camera/examples/recorded.toml --connect tcp/127.0.0.1:7447

The sequence folder::

    frames/frame-NNNNNN.color.png    the image (.jpg / .jpeg also taken), in frame-number order
    frames/frame-NNNNNN.pose.txt     4x4 T_world_cam (camera to world, metres, OpenCV camera axes)
    camera-intrinsics.txt            the 3x3 K in its first three rows, whitespace separated (another name:
                                     "intrinsics_file" in the config or meta.json)
    meta.json                        optional: "rate_hz" (the recorded frame rate), the declared pose
                                     accuracy "pose_sigma_trans_m" / "pose_sigma_rot_deg",
                                     "world_from_recording" (below) and "intrinsics_file"; other keys
                                     (depth_divisor, licence, pose_source...) are ignored

Each frame carries its intrinsics (K at the image's size) and its pose, checked with
:func:`protocol.poses.check_pose`. Recorded poses are priors (``pose_trusted = false``). With a declared
accuracy (config, else meta.json; both sigmas or neither) each frame also carries the 6x6
``pose_covariance`` the mapper reads as that pose's accuracy; without one there is none and the mapper
judges the poses from the images. A calibration file's intrinsics and pose still override these.

**World frame.** Argus's world has z up (against gravity) and the floor at z = 0: rooms, the floor-slab check
of fusion and relations such as "on" rely on it. A recording whose poses live in another frame (a HoloLens or
ARKit session is y-up, a SLAM run starts wherever its first camera was) states the rigid 4x4
``world_from_recording`` (config, else meta.json) that takes its frame to Argus's; every pose is sent as
``world_from_recording @ T_world_cam``. Without one the poses are sent as recorded, and a recording whose
cameras' mean image-down direction is more than :data:`UP_WARN_DEG` from world -z is warned about when built
(:func:`down_angle_deg`), since its keyframes would mostly be rejected as depth under the floor.

The header's ``source_kind`` stays ``"fixed"``: it is the camera's own key (the ACL lets a camera put only
its own cam keys). A pose per frame with ``pose_trusted = false`` is what tells the mapper this camera
moves.

A folder that can never play (no ``frames/``, no frames, a missing or unreadable
``camera-intrinsics.txt``, a bad ``meta.json``, no frame with a usable pose) is a
:class:`SourceConfigError` when the source is built. A frame whose pose file is missing or bad, or whose
image is unreadable, is skipped with a warning naming the file and counted in ``skipped``. After the last
frame the recording starts over at ``start`` (``loop = true``) or ends: every later read is a
:class:`SourceError` saying so, and a reopen after that fault does not replay it.
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import Field, model_validator

from edge_camera.pose_accuracy import declared_covariance
from edge_camera.sources.base import Grab, SourceBase, SourceConfig, SourceConfigError, SourceError
from protocol.messages import Intrinsics
from protocol.poses import PoseCheck, check_pose

log = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 5.0
"""Frames per second when neither the config nor meta.json gives a rate."""
DEFAULT_INTRINSICS_FILE = "camera-intrinsics.txt"
"""The file holding K when neither the config nor meta.json names another."""
UP_WARN_DEG = 60.0
"""A recording without ``world_from_recording`` whose cameras look, on average, this far off level is warned about."""
_COLOR = re.compile(r"^frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)


class Config(SourceConfig):
    type: Literal["recorded"] = Field(default="recorded", description="recorded sequence with per-frame poses")
    path: Path = Field(description="sequence folder: frames/, camera-intrinsics.txt, optional meta.json")
    rate_hz: float | None = Field(
        default=None, gt=0, description=f"frames per second; default: meta.json's rate_hz, else {DEFAULT_RATE_HZ:g}"
    )
    loop: bool = Field(default=False, description="start over at 'start' after the last frame; false: end there")
    start: int = Field(default=0, ge=0, description="first frame played, an index into the sorted frame list")
    stop: int | None = Field(
        default=None, ge=1, description="index after the last frame played (exclusive); default: to the end"
    )
    pose_sigma_trans_m: float | None = Field(
        default=None, gt=0, allow_inf_nan=False,
        description="declared std-dev of each pose position axis, metres (with pose_sigma_rot_deg; default: "
        "meta.json's, else no declaration: frames carry no pose covariance)",
    )
    pose_sigma_rot_deg: float | None = Field(
        default=None, gt=0, allow_inf_nan=False,
        description="declared std-dev of each pose rotation axis, degrees (with pose_sigma_trans_m)",
    )
    intrinsics_file: str | None = Field(
        default=None, min_length=1,
        description="file in the folder holding K; default: meta.json's intrinsics_file, else camera-intrinsics.txt",
    )
    world_from_recording: list[list[float]] | None = Field(
        default=None,
        description="rigid 4x4 taking the recording's world frame to Argus's (z up, floor at z = 0), applied to "
        "every pose; default: meta.json's, else the poses as recorded",
    )

    @model_validator(mode="after")
    def _consistent(self) -> Config:
        if (self.pose_sigma_trans_m is None) != (self.pose_sigma_rot_deg is None):
            raise ValueError("pose_sigma_trans_m and pose_sigma_rot_deg go together (both or neither)")
        if self.stop is not None and self.stop <= self.start:
            raise ValueError(f"stop ({self.stop}) must be greater than start ({self.start})")
        if self.world_from_recording is not None:
            world_transform(self.world_from_recording, "world_from_recording")  # raises ValueError when not rigid
        return self


@dataclass(frozen=True)
class RecordedFrame:
    """One playable frame: its image file and its checked pose."""

    image: Path
    T_world_cam: np.ndarray


def _fail(what: str) -> SourceConfigError:
    return SourceConfigError(f"recorded source: {what}")


def read_intrinsics_matrix(path: Path) -> np.ndarray:
    """The 3x3 K in the first three non-empty rows of ``path``; :class:`SourceConfigError` naming it if unusable."""
    try:
        lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()][:3]
    except OSError as e:
        raise _fail(f"cannot read {path}: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise _fail(f"{path} is not a text file") from None
    try:
        K = np.array(lines, dtype=np.float64)
    except ValueError:
        raise _fail(f"{path} must hold the 3x3 camera matrix K as three rows of three numbers") from None
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise _fail(f"{path} must hold the 3x3 camera matrix K as three rows of three finite numbers")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise _fail(f"{path}: focal lengths K[0,0] and K[1,1] must be > 0, got {K[0, 0]:g} and {K[1, 1]:g}")
    return K


def world_transform(value: Any, where: str) -> np.ndarray | None:
    """``world_from_recording`` as a checked rigid 4x4 (None when ``value`` is None); ``ValueError`` naming
    ``where`` when it is not a rigid transform."""
    if value is None:
        return None
    return check_pose(value, source=f"{where} (world_from_recording)").T


def down_angle_deg(poses: list[np.ndarray]) -> float:
    """Angle between the cameras' mean image-down direction (the y axis of OpenCV camera axes, in the world
    frame) and world -z, degrees: near 0 for an upright camera in a z-up world (a camera pitched 30 deg down
    still reads about 30), near 90 for a y-up world such as a HoloLens or ARKit session's; NaN without poses."""
    if not poses:
        return math.nan
    down = np.mean([np.asarray(T, np.float64)[:3, 1] for T in poses], axis=0)
    n = float(np.linalg.norm(down))
    if n < 1e-9:
        return 90.0
    return math.degrees(math.acos(float(np.clip(-down[2] / n, -1.0, 1.0))))


def read_meta(path: Path) -> dict[str, Any]:
    """meta.json as a dict (empty when absent); :class:`SourceConfigError` naming it when it is bad."""
    if not path.exists():
        return {}
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise _fail(f"cannot read {path}: {e}") from None
    except json.JSONDecodeError as e:
        raise _fail(f"{path} is not valid JSON: {e}") from None
    if not isinstance(meta, dict):
        raise _fail(f"{path} must hold a JSON object")
    for key in ("rate_hz", "pose_sigma_trans_m", "pose_sigma_rot_deg"):
        v = meta.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0):
            raise _fail(f"{path}: {key} must be a number > 0, got {v!r}")
    name = meta.get("intrinsics_file")
    if name is not None and (not isinstance(name, str) or not name):
        raise _fail(f"{path}: intrinsics_file must be a file name, got {name!r}")
    try:
        world_transform(meta.get("world_from_recording"), str(path))
    except ValueError as e:
        raise _fail(str(e)) from None
    return meta


def read_pose(path: Path) -> PoseCheck:
    """The checked 4x4 pose in ``path`` (``.T``; ``.projected`` when its rotation was projected onto SO(3));
    ``ValueError`` (PoseError or a parse error) naming it when unusable."""
    try:
        T = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except OSError as e:
        raise ValueError(f"cannot read pose file {path}: {e.strerror or e}") from None
    except ValueError as e:
        raise ValueError(f"pose file {path} is not a matrix of numbers: {e}") from None
    return check_pose(T, source=f"pose file {path}")


def list_color_images(frames_dir: Path) -> list[Path]:
    """``frame-NNNNNN.color.*`` images of a frames folder in frame-number order (png before jpg of one frame)."""
    by_number: dict[int, Path] = {}
    for p in sorted(frames_dir.iterdir(), key=lambda q: (q.name.lower().endswith(".png") is False, q.name)):
        m = _COLOR.match(p.name)
        if m and p.is_file():
            by_number.setdefault(int(m.group(1)), p)
    return [by_number[n] for n in sorted(by_number)]


class RecordedSequence(SourceBase):
    """Plays the frames of a sequence folder; the folder is read (poses, K, meta.json) when built."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.skipped = 0
        folder = config.path
        frames_dir = folder / "frames"
        if not frames_dir.is_dir():
            raise _fail(f"{frames_dir} does not exist (a sequence folder holds frames/ and camera-intrinsics.txt)")
        images = list_color_images(frames_dir)
        if not images:
            raise _fail(f"{frames_dir} holds no frame-NNNNNN.color.png / .jpg images")
        meta = read_meta(folder / "meta.json")
        self.K = read_intrinsics_matrix(folder / (config.intrinsics_file or meta.get("intrinsics_file")
                                                  or DEFAULT_INTRINSICS_FILE))
        self.rate_hz = config.rate_hz or meta.get("rate_hz") or DEFAULT_RATE_HZ
        if config.pose_sigma_trans_m is not None and config.pose_sigma_rot_deg is not None:
            self.pose_covariance = declared_covariance(config.pose_sigma_trans_m, config.pose_sigma_rot_deg, "config")
        else:
            try:
                self.pose_covariance = declared_covariance(
                    meta.get("pose_sigma_trans_m"), meta.get("pose_sigma_rot_deg"), str(folder / "meta.json"))
            except ValueError as e:
                raise _fail(str(e)) from None
        given = config.world_from_recording if config.world_from_recording is not None else meta.get(
            "world_from_recording")
        self.world_from_recording = world_transform(given, "config" if config.world_from_recording is not None
                                                    else str(folder / "meta.json"))
        chosen = images[config.start:config.stop]
        if not chosen:
            raise _fail(f"start = {config.start} is past the last of the {len(images)} frames in {frames_dir}")
        self.frames: list[RecordedFrame] = []
        for image in chosen:
            pose_path = image.with_name(image.name.split(".", 1)[0] + ".pose.txt")
            try:
                T = read_pose(pose_path).T
            except ValueError as e:  # PoseError included
                self._skip(f"skipping frame {image.name}: {e}")
                continue
            W = self.world_from_recording
            self.frames.append(RecordedFrame(image, T if W is None else check_pose(W @ T, str(pose_path)).T))
        if not self.frames:
            raise _fail(f"no frame of {folder} has a usable pose file (see the warnings above)")
        tilt = down_angle_deg([f.T_world_cam for f in self.frames])
        if self.world_from_recording is None and tilt > UP_WARN_DEG:
            log.warning("%s: the cameras look %.0f deg off level on average: this recording's world frame does not "
                        "look z-up. Argus's world has z up and the floor at z = 0; state world_from_recording in "
                        "meta.json or the source config (docs/deploy.md, 'Record one')", folder, tilt)
        self._index = 0  # kept across close/open, so a reopen resumes instead of replaying
        self._open = False
        self._ended = False

    def _skip(self, why: str) -> None:
        self.skipped += 1
        log.warning("%s", why)

    def _end_message(self) -> str:
        return f"end of recording {self.config.path} (loop = false); it is not replayed"

    def open(self) -> None:
        self._open = True

    def read(self) -> Grab:
        if not self._open:
            raise SourceError("recorded source not open")
        while self.frames:
            if self._ended:
                raise SourceError(self._end_message())
            if self._index >= len(self.frames):
                if not self.config.loop:
                    self._ended = True
                    raise SourceError(self._end_message())
                self._index = 0
            frame = self.frames[self._index]
            bgr = cv2.imread(str(frame.image), cv2.IMREAD_COLOR)
            if bgr is None:
                # Dropped, not retried: a recording does not repair itself, and a loop would warn each pass.
                del self.frames[self._index]
                self._skip(f"skipping unreadable image {frame.image}")
                continue
            self._index += 1
            h, w = bgr.shape[:2]
            K = self.K
            intr = Intrinsics(width=w, height=h, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
            return Grab(rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), stamp_ns=time.time_ns(), intrinsics=intr,
                        T_world_cam=frame.T_world_cam, pose_trusted=False, pose_covariance=self.pose_covariance)
        raise _fail(f"no frame of {self.config.path} is readable (see the warnings above)")

    def close(self) -> None:
        self._open = False


def create(config: Config) -> RecordedSequence:
    return RecordedSequence(config)
