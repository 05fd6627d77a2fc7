"""A fixed camera high in a room corner looking down at boxes on the floor: ``box()`` places one,
``silhouette()`` draws its image mask from the projected corners (independent of ray casting)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from mapper.geometry.singleview import PlacedBox
from protocol.messages import Intrinsics
from protocol.poses import look_at

INTR = Intrinsics.from_fov(640, 480, 90.0)
K = INTR.K()
CAM = look_at([0.2, 0.3, 2.5], [3.0, 2.5, 0.3])  # a fixed camera high in a room corner, looking down


def box(cx: float, cy: float, z0: float, ex: float, ey: float, h: float, yaw_deg: float = 0.0) -> PlacedBox:
    return PlacedBox(np.array([cx, cy, z0 + h / 2]), np.array([ex, ey, h]), math.radians(yaw_deg), -1, 0)


def silhouette(b: PlacedBox, T_world_cam: np.ndarray = CAM) -> np.ndarray:
    """The box's image mask drawn as the convex hull of its projected corners (independent of ray casting)."""
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    pc = (b.corners() - t) @ R
    uv = pc[:, :2] / pc[:, 2:3] * np.diag(K)[:2] + K[:2, 2]
    mask = np.zeros((INTR.height, INTR.width), np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.round(uv).astype(np.int32)), 1)
    return mask.astype(bool)
