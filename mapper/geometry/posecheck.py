"""Has a fixed camera moved since its pose was surveyed? (pure: arrays in, numbers out)

A bumped camera keeps streaming, and every object it places afterwards would land in the wrong spot. A
fixed camera that is knocked mostly turns about its mount, so its new image is the old one under the
homography ``H = K R K^-1`` of that rotation (exact for a pure rotation whatever the scene depth). Matching
the camera's reference keyframe to a new one, fitting ``H`` robustly (people walking by are outliers) and
reading the rotation out of ``K^-1 H K`` measures how far it turned; an unmoved camera gives ~0 deg.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mapper.geometry.features import Features, match_features
from protocol.poses import rotation_angle_deg

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class RotationCheck:
    """``rotation_deg``: how far the camera turned between the two images (None when too few features
    agree to say); ``inliers``: matches consistent with the fitted homography; ``matches``: all matches."""

    rotation_deg: float | None
    inliers: int
    matches: int


def rotation_between(ref: Features, cur: Features, K: F64, min_inliers: int = 40,
                     reproj_px: float = 2.0) -> RotationCheck:
    """Rotation of a static camera between a reference image's features and a new image's (same ``K``)."""
    m = match_features(ref, cur)
    if len(m) < min_inliers:
        return RotationCheck(None, 0, len(m))
    H, mask = cv2.findHomography(ref.uv[m[:, 0]], cur.uv[m[:, 1]], cv2.RANSAC, reproj_px)
    if H is None or mask is None:
        return RotationCheck(None, 0, len(m))
    n = int(mask.sum())
    if n < min_inliers:
        return RotationCheck(None, n, len(m))
    M = np.linalg.inv(K) @ H @ K
    det = float(np.linalg.det(M))
    if abs(det) < 1e-12:
        return RotationCheck(None, n, len(m))
    M /= np.cbrt(det)
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return RotationCheck(rotation_angle_deg(np.eye(3), R), n, len(m))
