"""Pose and camera conventions shared by every Argus package (written once, here).

Conventions
-----------
* World frame: metres, right-handed, **z up**; the floor is the plane z = 0.
* Camera frame: OpenCV axes, x right, y down, z forward (the optical axis).
* A pose ``T_a_b`` is a 4x4 homogeneous matrix mapping points in frame ``b`` into frame ``a``:
  ``p_a = T_a_b @ p_b``. ``T_world_cam`` is therefore the camera's pose in the world.
* A robot base pose is ``(x, y, yaw_rad)`` on the floor; ``yaw = 0`` faces world +x and yaw grows
  counter-clockwise seen from above. Its camera sits ``height_m`` above the floor looking along the
  heading, tilted by ``pitch_deg`` (negative looks down).
* Pixel coordinates: ``(u, v)`` with u to the right and v down; the centre of the top-left pixel is
  (0, 0).

Everything here is pure numpy with no I/O.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def as_pose(T: ArrayLike) -> F64:
    """Return ``T`` as a float64 4x4 array, raising ``ValueError`` if it is not a finite rigid pose."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"a pose must be 4x4, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError("a pose must be finite")
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise ValueError("a pose's last row must be [0, 0, 0, 1]")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0.0:
        raise ValueError("a pose's rotation must be orthonormal with determinant +1")
    return M


def make_pose(R: ArrayLike, t: ArrayLike) -> F64:
    """Build ``T`` from a 3x3 rotation and a translation 3-vector."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T_a_b: ArrayLike) -> F64:
    """Invert a rigid pose: ``invert(T_a_b) == T_b_a`` (uses the transpose, not a general inverse)."""
    T = np.asarray(T_a_b, dtype=np.float64)
    R = T[:3, :3]
    t = T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def transform_points(T_a_b: ArrayLike, points_b: ArrayLike) -> F64:
    """Map points ``(..., 3)`` from frame b into frame a."""
    T = np.asarray(T_a_b, dtype=np.float64)
    p = np.asarray(points_b, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def rot_z(yaw_rad: float) -> F64:
    """Rotation about the world z axis by ``yaw_rad`` (counter-clockwise seen from above)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_pose_from_base(x: float, y: float, yaw_rad: float, height_m: float, pitch_deg: float = 0.0) -> F64:
    """``T_world_cam`` of a camera mounted on a base at ``(x, y, yaw)``, ``height_m`` above the floor.

    The camera looks along the base heading, tilted by ``pitch_deg`` (negative looks down).
    """
    # Camera axes (x right, y down, z forward) for a level camera facing world +x:
    # cam z -> world +x, cam x -> world -y, cam y -> world -z.
    R_base_cam0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    p = np.deg2rad(pitch_deg)
    # Pitch is a rotation about the camera x axis; positive pitch_deg tilts the view up.
    c, s = np.cos(p), np.sin(p)
    R_cam0_cam = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    R = rot_z(yaw_rad) @ R_base_cam0 @ R_cam0_cam
    return make_pose(R, [x, y, height_m])


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> F64:
    """``T_world_cam`` of a camera at ``eye`` whose optical axis points at ``target``."""
    eye_v = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye_v
    n = np.linalg.norm(z)
    if n < 1e-9:
        raise ValueError("look_at needs target != eye")
    z /= n
    up_v = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up_v)  # camera x (right) = forward x up
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # camera y points down
    return make_pose(np.stack([x, y, z], axis=1), eye_v)


def yaw_of(T_world_cam: ArrayLike) -> float:
    """Heading (radians) of a camera's optical axis projected on the floor."""
    z = np.asarray(T_world_cam, dtype=np.float64)[:3, 2]
    return float(np.arctan2(z[1], z[0]))


def rotation_angle_deg(R_a: ArrayLike, R_b: ArrayLike) -> float:
    """Angle in degrees of the relative rotation ``R_a^T R_b``."""
    R = np.asarray(R_a, dtype=np.float64)[:3, :3].T @ np.asarray(R_b, dtype=np.float64)[:3, :3]
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> F64:
    """The 3x3 pinhole matrix K."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def project(K: ArrayLike, points_cam: ArrayLike) -> tuple[F64, F64]:
    """Project camera-frame points ``(N, 3)`` to pixels ``(N, 2)``; also returns their z depth."""
    Km = np.asarray(K, dtype=np.float64)
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p[:, :2] / z[:, None]) * np.diag(Km)[:2] + Km[:2, 2]
    return uv, z


def unproject(K: ArrayLike, uv: ArrayLike, depth_m: ArrayLike) -> F64:
    """Back-project pixels ``(N, 2)`` with z depth ``(N,)`` into camera-frame points ``(N, 3)``."""
    Km = np.asarray(K, dtype=np.float64)
    uv_a = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(depth_m, dtype=np.float64).reshape(-1)
    x = (uv_a[:, 0] - Km[0, 2]) / Km[0, 0] * d
    y = (uv_a[:, 1] - Km[1, 2]) / Km[1, 1] * d
    return np.stack([x, y, d], axis=1)
