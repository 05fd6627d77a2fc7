from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol import poses
from protocol.messages import Intrinsics

angles = st.floats(-np.pi, np.pi)
coords = st.floats(-50, 50)


@given(coords, coords, angles, st.floats(0.1, 3), st.floats(-80, 80))
def test_pose_times_inverse_is_identity(x: float, y: float, yaw: float, h: float, pitch: float) -> None:
    T = poses.camera_pose_from_base(x, y, yaw, h, pitch)
    poses.as_pose(T)
    assert np.allclose(T @ poses.invert(T), np.eye(4), atol=1e-9)


def test_level_camera_looks_along_heading() -> None:
    T = poses.camera_pose_from_base(1.0, 2.0, np.pi / 2, 1.5, 0.0)
    assert np.allclose(T[:3, 2], [0, 1, 0], atol=1e-12)  # optical axis = world +y
    assert np.allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # image down = world down
    assert np.allclose(T[:3, 3], [1, 2, 1.5])
    assert poses.yaw_of(T) == pytest.approx(np.pi / 2)


def test_negative_pitch_looks_down() -> None:
    T = poses.camera_pose_from_base(0, 0, 0, 1.0, -30.0)
    assert np.allclose(T[:3, 2], [np.cos(np.radians(30)), 0, -np.sin(np.radians(30))], atol=1e-12)


def test_project_then_unproject() -> None:
    K = Intrinsics.from_fov(640, 480, 90).K()
    pts = np.array([[0.1, -0.2, 2.0], [1.0, 0.5, 3.0], [0.0, 0.0, 1.0]])
    uv, z = poses.project(K, pts)
    assert np.allclose(uv[2], [319.5, 239.5])
    assert np.allclose(poses.unproject(K, uv, z), pts)


def test_look_at_points_the_optical_axis() -> None:
    T = poses.look_at([0, 0, 2.5], [3, 4, 0])
    d = np.array([3, 4, -2.5]) / np.linalg.norm([3, 4, -2.5])
    assert np.allclose(T[:3, 2], d)
    assert T[:3, 1] @ np.array([0, 0, 1]) < 0  # image down points downwards-ish
    p_cam = poses.transform_points(poses.invert(T), [3, 4, 0])
    assert np.allclose(p_cam[:2], 0, atol=1e-9) and p_cam[2] > 0


def test_as_pose_rejects_non_rigid() -> None:
    with pytest.raises(ValueError):
        poses.as_pose(np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError):
        poses.as_pose(np.eye(3))


def test_intrinsics_scaling_keeps_the_principal_ray() -> None:
    K = Intrinsics.from_fov(640, 480, 90)
    half = K.scaled(160, 120)
    assert half.fx == pytest.approx(K.fx / 4)
    assert half.cx == pytest.approx(79.5) and half.cy == pytest.approx(59.5)
