"""Camera calibration files: intrinsics and (optionally) the surveyed pose ``T_world_cam``.

Two formats, picked by the file ending:

* OpenCV YAML/XML (``.yaml``, ``.yml``, ``.xml``; read with ``cv2.FileStorage``), as written by
  OpenCV's calibration tools: ``camera_matrix`` (or ``K``) 3x3, ``image_width``, ``image_height``,
  optional ``T_world_cam`` 4x4 (world frame z up, OpenCV camera axes, see ``protocol.poses``).
* JSON: ``{"intrinsics": {"width", "height", "fx", "fy", "cx", "cy"}, "T_world_cam": [[...] x4]}``;
  ``camera_matrix`` + ``image_width`` + ``image_height`` are accepted instead of ``intrinsics``.

Either part may be absent, not both. A calibration's pose is trusted (``pose_trusted = true``).

The pose's accuracy may be stated in both formats with the keys ``pose_sigma_trans_m`` (standard
deviation of each position axis, metres) and ``pose_sigma_rot_deg`` (of each rotation axis, degrees),
both or neither, both > 0, and only next to a ``T_world_cam``. Stated, the frame header carries
:func:`edge_camera.pose_accuracy.pose_covariance` of them and the mapper takes the pose as that
accurate; unstated, the header has no covariance and the mapper judges the pose from the images.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from edge_camera.pose_accuracy import declared_covariance
from protocol.messages import Intrinsics
from protocol.poses import PoseError, as_pose


class CalibrationError(ValueError):
    """An unreadable or inconsistent calibration file."""


@dataclass(frozen=True)
class Calibration:
    """What a calibration file says: intrinsics at ``intrinsics.width x height`` and/or the pose.

    ``pose_covariance``: ``(6, 6)`` covariance of ``T_world_cam`` (x y z roll pitch yaw; m^2, rad^2) when the
    file states the pose's accuracy, else None.
    """

    intrinsics: Intrinsics | None
    T_world_cam: np.ndarray | None
    distortion: np.ndarray | None = None
    pose_covariance: np.ndarray | None = None


def _covariance(sigma_trans_m: Any, sigma_rot_deg: Any, path: Path) -> np.ndarray | None:
    try:
        return declared_covariance(sigma_trans_m, sigma_rot_deg, f"calibration file {path}")
    except ValueError as e:
        raise CalibrationError(str(e)) from None


def _intrinsics_from_matrix(K: Any, width: Any, height: Any) -> Intrinsics:
    Km = np.asarray(K, dtype=np.float64)
    if Km.shape != (3, 3):
        raise CalibrationError(f"camera_matrix must be 3x3, got shape {Km.shape}")
    if width is None or height is None:
        raise CalibrationError("camera_matrix needs image_width and image_height")
    return Intrinsics(
        width=int(width), height=int(height), fx=Km[0, 0], fy=Km[1, 1], cx=Km[0, 2], cy=Km[1, 2]
    )


def _from_yaml(path: Path) -> Calibration:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except Exception as e:  # noqa: BLE001 - cv2 raises cv2.error or SystemError on a bad file
        raise CalibrationError(f"cannot parse calibration file {path}: {e}") from None
    if not fs.isOpened():
        raise CalibrationError(f"cannot parse calibration file {path} as OpenCV YAML/XML")
    try:

        def mat(*names: str) -> np.ndarray | None:
            for n in names:
                node = fs.getNode(n)
                if not node.empty():
                    m = node.mat()
                    if m is None:
                        raise CalibrationError(f"{n} in {path} is not a matrix")
                    return np.asarray(m, dtype=np.float64)
            return None

        def num(name: str) -> float | None:
            node = fs.getNode(name)
            return None if node.empty() else node.real()

        K = mat("camera_matrix", "K")
        T = mat("T_world_cam")
        dist = mat("distortion_coefficients", "dist_coeffs")
        intr = _intrinsics_from_matrix(K, num("image_width"), num("image_height")) if K is not None else None
        cov = _covariance(num("pose_sigma_trans_m"), num("pose_sigma_rot_deg"), path)
    finally:
        fs.release()
    return Calibration(intr, T, dist, cov)


def _from_json(path: Path) -> Calibration:
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise CalibrationError(f"calibration file {path} is not valid JSON: {e}") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a JSON object")
    unknown = set(data) - {"intrinsics", "camera_matrix", "image_width", "image_height", "T_world_cam",
                           "distortion_coefficients", "pose_sigma_trans_m", "pose_sigma_rot_deg"}
    if unknown:
        raise CalibrationError(f"{path}: unknown fields {sorted(unknown)}")
    intr: Intrinsics | None = None
    if data.get("intrinsics") is not None:
        intr = Intrinsics.model_validate(data["intrinsics"])
    elif data.get("camera_matrix") is not None:
        intr = _intrinsics_from_matrix(data["camera_matrix"], data.get("image_width"), data.get("image_height"))
    T = data.get("T_world_cam")
    dist = data.get("distortion_coefficients")
    return Calibration(
        intr,
        None if T is None else np.asarray(T, dtype=np.float64),
        None if dist is None else np.asarray(dist, dtype=np.float64),
        _covariance(data.get("pose_sigma_trans_m"), data.get("pose_sigma_rot_deg"), path),
    )


def load_calibration(path: Path) -> Calibration:
    """Read a calibration file; :class:`CalibrationError` with the reason when unusable."""
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} does not exist")
    try:
        calib = _from_json(path) if path.suffix.lower() == ".json" else _from_yaml(path)
    except CalibrationError:
        raise
    except Exception as e:  # noqa: BLE001 - pydantic, numpy or cv2 errors on a hostile file
        raise CalibrationError(f"calibration file {path}: {e}") from None
    if calib.intrinsics is None and calib.T_world_cam is None:
        raise CalibrationError(f"calibration file {path} holds neither camera_matrix nor T_world_cam")
    if calib.pose_covariance is not None and calib.T_world_cam is None:
        raise CalibrationError(f"calibration file {path} states pose_sigma_trans_m / pose_sigma_rot_deg but no "
                               "T_world_cam they would describe")
    if calib.T_world_cam is not None:
        try:
            # A surveyed pose written with a few decimals is projected onto SO(3) here, once.
            calib = replace(calib, T_world_cam=as_pose(calib.T_world_cam, source=f"T_world_cam in {path}"))
        except PoseError as e:
            raise CalibrationError(str(e)) from None
    return calib
