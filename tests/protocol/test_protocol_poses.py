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


SRC = "robot-1 frame 42 pose"
T_GOOD = poses.camera_pose_from_base(1.0, -2.0, 0.7, 1.2, -20.0)


def with_rotation(R: np.ndarray, T: np.ndarray = T_GOOD) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = R
    return out


def residual(R: np.ndarray) -> float:
    return float(np.linalg.norm(R.T @ R - np.eye(3)))


def in_so3(R: np.ndarray, atol: float = 1e-12) -> bool:
    return residual(R) <= atol and abs(np.linalg.det(R) - 1.0) <= atol


@st.composite
def rotations(draw: st.DrawFn) -> np.ndarray:
    """A rotation from a random non-zero quaternion."""
    q = np.array(draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4)))
    if np.linalg.norm(q) < 1e-3:
        q = np.array([1.0, 0.0, 0.0, 0.0])
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


class TestCheckPose:
    def test_exactly_orthonormal_is_kept_and_not_flagged(self) -> None:
        c = poses.check_pose(T_GOOD, SRC)
        assert not c.projected and c.residual < 1e-14
        np.testing.assert_array_equal(c.T, T_GOOD)
        assert c.T is not T_GOOD and c.T.dtype == np.float64

    def test_eye_as_integers_is_a_float_pose(self) -> None:
        c = poses.check_pose(np.eye(4, dtype=np.int64))
        assert c.T.dtype == np.float64 and not c.projected and c.residual == 0.0

    def test_scaled_by_5e_4_is_projected_back(self) -> None:
        R = T_GOOD[:3, :3]
        c = poses.check_pose(with_rotation(R * (1 + 5e-4)), SRC)
        assert c.projected
        assert c.residual == pytest.approx(np.sqrt(3) * ((1 + 5e-4) ** 2 - 1), rel=1e-9)
        assert in_so3(c.T[:3, :3])
        np.testing.assert_allclose(c.T[:3, :3], R, atol=1e-12)  # a uniform scale projects to R itself
        np.testing.assert_array_equal(c.T[:3, 3], T_GOOD[:3, 3])  # the translation is untouched
        np.testing.assert_array_equal(c.T[3], [0, 0, 0, 1])

    def test_1e_3_noise_is_projected_to_a_rotation_nearby(self) -> None:
        rng = np.random.default_rng(3)
        M = T_GOOD[:3, :3] + rng.uniform(-1e-3, 1e-3, (3, 3))
        T_in = with_rotation(M)
        c = poses.check_pose(T_in, SRC)
        assert c.projected and 1e-4 < c.residual < poses.ROTATION_TOLERANCE
        assert in_so3(c.T[:3, :3])
        assert np.abs(c.T[:3, :3] - T_GOOD[:3, :3]).max() < 2e-3
        np.testing.assert_array_equal(T_in[:3, :3], M)  # the caller's array is not changed

    def test_six_decimal_dataset_pose_is_accepted(self) -> None:
        T6 = np.round(T_GOOD, 6)
        c = poses.check_pose(T6, SRC)
        assert c.projected and c.residual < 1e-5 and in_so3(c.T[:3, :3])
        np.testing.assert_allclose(poses.as_pose(T6), c.T, atol=0)

    def test_last_row_within_tolerance_is_cleaned(self) -> None:
        T = T_GOOD.copy()
        T[3, :3] = 5e-7
        np.testing.assert_array_equal(poses.check_pose(T).T[3], [0, 0, 0, 1])

    @pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
    def test_non_finite_is_refused(self, bad: float) -> None:
        T = T_GOOD.copy()
        T[1, 3] = bad
        with pytest.raises(poses.PoseError, match=rf"^{SRC}: .*finite.*\[1, 3\]"):
            poses.check_pose(T, SRC)

    def test_shear_is_refused_with_its_residual(self) -> None:
        S = np.array([[1, 0.05, 0], [0, 1, 0], [0, 0, 1]])
        M = T_GOOD[:3, :3] @ S
        r = residual(M)
        assert r == pytest.approx(np.sqrt(2 * 0.05**2 + 0.05**4))
        with pytest.raises(poses.PoseError) as e:
            poses.check_pose(with_rotation(M), SRC)
        msg = str(e.value)
        assert msg.startswith(f"{SRC}: ") and "not orthonormal" in msg and f"= {r:.3g} > 0.01" in msg
        assert f"{r:.3g}" == "0.0708"

    def test_scaled_rotation_is_refused(self) -> None:
        with pytest.raises(poses.PoseError, match=rf"^{SRC}: .*not orthonormal .*= 0\.0\d+ > 0\.01"):
            poses.check_pose(with_rotation(T_GOOD[:3, :3] * 1.01), SRC)

    def test_reflection_is_refused(self) -> None:
        M = T_GOOD[:3, :3] @ np.diag([1.0, 1.0, -1.0])
        assert residual(M) < 1e-14  # orthonormal: only the determinant tells
        with pytest.raises(poses.PoseError, match=rf"^{SRC}: .*reflection.*det R = -1 <= 0"):
            poses.check_pose(with_rotation(M), SRC)

    def test_degenerate_rotation_is_refused(self) -> None:
        with pytest.raises(poses.PoseError, match=rf"^{SRC}: .*det R = 0 <= 0"):
            poses.check_pose(with_rotation(np.zeros((3, 3))), SRC)

    @pytest.mark.parametrize(("shape", "hint"), [((3, 3), "bare rotation"), ((3, 4), r"\[R \| t\]"),
                                                 ((4,), ""), ((2, 4, 4), "")])
    def test_wrong_shape_is_refused(self, shape: tuple[int, ...], hint: str) -> None:
        with pytest.raises(poses.PoseError, match=rf"^{SRC}: .*4x4.*got shape \({shape[0]},.*{hint}"):
            poses.check_pose(np.zeros(shape), SRC)

    def test_wrong_last_row_is_refused(self) -> None:
        T = T_GOOD.copy()
        T[3] = [0, 0, 1e-3, 1]
        with pytest.raises(poses.PoseError, match=rf"^{SRC}: .*last row"):
            poses.check_pose(T, SRC)

    def test_not_a_matrix_is_refused(self) -> None:
        with pytest.raises(poses.PoseError, match=rf"^{SRC}: not a numeric matrix"):
            poses.check_pose([[1, 2], [3]], SRC)  # type: ignore[list-item]

    def test_overflowing_entries_are_refused_without_warnings(self) -> None:
        with np.errstate(all="raise"):
            with pytest.raises(poses.PoseError, match="not orthonormal"):
                poses.check_pose(with_rotation(np.full((3, 3), 1e200) * np.eye(3)), SRC)

    def test_as_pose_is_check_pose_and_names_the_default_source(self) -> None:
        with pytest.raises(poses.PoseError, match=r"^pose: "):
            poses.as_pose(np.eye(3))
        with pytest.raises(poses.PoseError, match=r"^calib\.json: "):
            poses.as_pose(np.eye(3), source="calib.json")
        assert issubclass(poses.PoseError, ValueError)

    @given(rotations(), st.lists(st.floats(-1e-3, 1e-3), min_size=9, max_size=9))
    def test_projection_lands_in_so3_and_is_nearest(self, R: np.ndarray, noise: list[float]) -> None:
        M = R + np.reshape(noise, (3, 3))
        assert residual(M) <= poses.ROTATION_TOLERANCE  # |noise| <= 1e-3 keeps it under the tolerance
        c = poses.check_pose(with_rotation(M))
        Q = c.T[:3, :3]
        assert c.residual == pytest.approx(residual(M), abs=1e-15)
        assert c.projected == (c.residual > poses.PROJECTION_THRESHOLD)
        assert in_so3(Q, atol=1e-12 if c.projected else 1e-9)
        # The nearest rotation: no farther from M than the rotation the noise was added to.
        assert np.linalg.norm(Q - M) <= np.linalg.norm(R - M) + 1e-12


def test_intrinsics_scaling_keeps_the_principal_ray() -> None:
    K = Intrinsics.from_fov(640, 480, 90)
    half = K.scaled(160, 120)
    assert half.fx == pytest.approx(K.fx / 4)
    assert half.cx == pytest.approx(79.5) and half.cy == pytest.approx(59.5)
