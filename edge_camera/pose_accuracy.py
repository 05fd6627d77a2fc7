"""A declared pose accuracy (standard deviations in metres and degrees) as the header's 6x6 covariance.

The frame header's ``pose_covariance`` is ordered x y z roll pitch yaw, in m^2 and rad^2. The mapper
reads it as the accuracy of ``T_world_cam``; a frame without one is judged from its images. Pure: no I/O.
"""

from __future__ import annotations

import math

import numpy as np

from protocol.poses import covariance_from_accuracy


def pose_covariance(sigma_trans_m: float, sigma_rot_deg: float) -> np.ndarray:
    """``(6, 6)`` diagonal covariance ``diag([st^2] * 3 + [radians(sr)^2] * 3)``.

    Every translation axis has standard deviation ``sigma_trans_m`` and every rotation axis
    ``sigma_rot_deg``, independent of each other. Both must be finite and > 0: a zero variance would
    claim an exact pose, which a consumer that inverts the covariance cannot use. Raises ``ValueError``.
    """
    for name, v in (("sigma_trans_m", sigma_trans_m), ("sigma_rot_deg", sigma_rot_deg)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0.0):
            raise ValueError(f"{name} must be finite and > 0, got {v!r}")
    return covariance_from_accuracy(float(sigma_trans_m), float(sigma_rot_deg))


def declared_covariance(sigma_trans_m: float | None, sigma_rot_deg: float | None, where: str) -> np.ndarray | None:
    """The covariance of a declaration that states both sigmas, None for one that states neither.

    One without the other is a ``ValueError`` naming ``where`` (e.g. the file that holds them).
    """
    if sigma_trans_m is None and sigma_rot_deg is None:
        return None
    if sigma_trans_m is None or sigma_rot_deg is None:
        raise ValueError(f"{where}: pose_sigma_trans_m and pose_sigma_rot_deg go together (both or neither)")
    try:
        return pose_covariance(sigma_trans_m, sigma_rot_deg)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
