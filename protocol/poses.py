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
* Pose tolerance: a pose read from outside (a header, a calibration file, a dataset) goes through
  :func:`check_pose`. Its rotation may be off orthonormal by up to ``ROTATION_TOLERANCE`` = 1e-2,
  measured as ``||R^T R - I||_F`` (poses written with 6 decimals are off by ~1e-6, float32 round trips
  by ~1e-7); such a rotation is replaced by the nearest rotation in SO(3) (SVD) and reported as
  projected. Anything further off (a shear, a scale), a reflection (det R <= 0), a non-finite entry, a
  last row other than [0, 0, 0, 1] (atol 1e-6) or a shape other than 4x4 is a :class:`PoseError`
  naming the pose's source.

Everything here is pure numpy with no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


ROTATION_TOLERANCE = 1e-2
"""Largest ``||R^T R - I||_F`` a pose's rotation may have; below it the rotation is projected onto SO(3)."""
PROJECTION_THRESHOLD = 1e-9
"""Residual above which a rotation counts as projected (float64 rounding of a true rotation is ~1e-15)."""
LAST_ROW_ATOL = 1e-6
"""How far a pose's last row may be from [0, 0, 0, 1], per entry."""


class PoseError(ValueError):
    """A matrix that is not a usable rigid pose; the message names its source and what is wrong."""


@dataclass(frozen=True)
class PoseCheck:
    """What :func:`check_pose` found.

    ``T``: the cleaned float64 4x4 pose (rotation in SO(3), last row exactly [0, 0, 0, 1], a new
    array). ``residual``: ``||R^T R - I||_F`` of the rotation as given. ``projected``: whether the
    rotation was replaced by its nearest rotation (``residual > PROJECTION_THRESHOLD``).
    """

    T: F64
    residual: float
    projected: bool


def nearest_rotation(M: ArrayLike) -> F64:
    """The rotation in SO(3) nearest to a 3x3 ``M`` in the Frobenius norm (SVD, reflection fixed)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    d = 1.0 if np.linalg.det(U @ Vt) > 0.0 else -1.0  # U Vt is orthogonal: det is +1 or -1
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def check_pose(T: ArrayLike, source: str = "pose") -> PoseCheck:
    """Validate and clean a rigid pose ``T`` (4x4, see the module's conventions for the tolerance).

    ``source`` names the pose in error messages, e.g. ``"robot-1 frame 42 pose"``. Raises
    :class:`PoseError` for a wrong shape, a non-finite entry, a wrong last row, a reflection or a
    rotation off orthonormal by more than ``ROTATION_TOLERANCE``.
    """
    try:
        M = np.array(T, dtype=np.float64)  # a copy: the caller's array is never changed
    except (TypeError, ValueError) as e:
        raise PoseError(f"{source}: not a numeric matrix ({e})") from None
    if M.shape != (4, 4):
        hint = {
            (3, 3): " (a 3x3 is a bare rotation or a camera matrix, not a pose)",
            (3, 4): " (a 3x4 is [R | t]: add the row [0, 0, 0, 1])",
        }.get(M.shape, "")
        raise PoseError(f"{source}: a pose must be a 4x4 homogeneous matrix, got shape {M.shape}{hint}")
    bad = ~np.isfinite(M)
    if bad.any():
        where = ", ".join(f"[{i}, {j}]" for i, j in np.argwhere(bad)[:4])
        raise PoseError(f"{source}: a pose must be finite, got NaN or inf at {where}")
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=LAST_ROW_ATOL):
        raise PoseError(f"{source}: a pose's last row must be [0, 0, 0, 1], got {M[3].tolist()}")
    R = M[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):
        det = float(np.linalg.det(R))
        residual = float(np.linalg.norm(R.T @ R - np.eye(3)))
    if not det > 0.0:
        raise PoseError(f"{source}: pose rotation is a reflection or degenerate (det R = {det:.3g} <= 0)")
    if not residual <= ROTATION_TOLERANCE:  # also catches a NaN residual (overflow)
        raise PoseError(
            f"{source}: pose rotation is not orthonormal (||R^T R - I|| = {residual:.3g} > "
            f"{ROTATION_TOLERANCE:g}): a shear or scale in the pose?"
        )
    projected = residual > PROJECTION_THRESHOLD
    if projected:
        M[:3, :3] = nearest_rotation(R)
    M[3] = [0.0, 0.0, 0.0, 1.0]
    return PoseCheck(T=M, residual=residual, projected=projected)


def as_pose(T: ArrayLike, source: str = "pose") -> F64:
    """``T`` as a clean float64 4x4 rigid pose (see :func:`check_pose`); raises :class:`PoseError`."""
    return check_pose(T, source).T


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


def wrap_angle(a: float) -> float:
    """An angle (radians) wrapped into [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


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


@dataclass(frozen=True)
class PoseAccuracy:
    """A pose's declared accuracy as standard deviations: the largest of its three position std-devs
    (metres) and of its three rotation std-devs (degrees)."""

    trans_m: float
    rot_deg: float


def pose_accuracy(covariance: ArrayLike, source: str = "pose covariance") -> PoseAccuracy:
    """Std-devs from a 6x6 pose covariance (order x y z roll pitch yaw; m^2 and rad^2, as
    ``FrameHeader.pose_covariance``). Only the diagonal is read. A shape other than 6x6, a non-finite
    entry or a negative variance is a :class:`PoseError` naming ``source``."""
    C = np.asarray(covariance, dtype=np.float64)
    if C.shape != (6, 6):
        raise PoseError(f"{source}: expected a 6x6 covariance, got shape {C.shape}")
    d = np.diag(C)
    if not np.all(np.isfinite(d)) or np.any(d < 0):
        raise PoseError(f"{source}: variances must be finite and >= 0, got {np.round(d, 9).tolist()}")
    return PoseAccuracy(float(np.sqrt(d[:3].max())), float(np.degrees(np.sqrt(d[3:].max()))))


def covariance_from_accuracy(trans_m: float, rot_deg: float) -> F64:
    """The diagonal 6x6 pose covariance (x y z roll pitch yaw) of position std-dev ``trans_m`` (metres, per
    axis) and rotation std-dev ``rot_deg`` (degrees, per axis): the inverse of :func:`pose_accuracy`."""
    if not (np.isfinite(trans_m) and np.isfinite(rot_deg) and trans_m >= 0 and rot_deg >= 0):
        raise PoseError(f"pose accuracy must be finite and >= 0, got {trans_m} m, {rot_deg} deg")
    return np.diag([trans_m**2] * 3 + [np.radians(rot_deg) ** 2] * 3).astype(np.float64)
