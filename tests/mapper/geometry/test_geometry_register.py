"""Pose estimation for cameras without extrinsics: PnP against mapped keyframes, two-view fallback, refusals."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.geometry.contract import View
from mapper.geometry.register import MapKeyframe, register_view, two_view_pose
from protocol.messages import Intrinsics
from protocol.poses import camera_pose_from_base, look_at, rotation_angle_deg

INTR = Intrinsics.from_fov(640, 480, 90.0)


@pytest.fixture(scope="module")
def rendered() -> dict:
    pytest.importorskip("sim.scene")
    from sim.render import Renderer
    from sim.scene import generate_scene

    scene = generate_scene("furnished_room", 2)
    renderer = Renderer(scene)
    cx, cy = (scene.bounds_min[:2] + scene.bounds_max[:2]) / 2
    lo = scene.bounds_min[:2]
    # Two robot keyframes near one corner looking at the room centre, and a higher "fixed" camera between them.
    yaw = float(np.arctan2(cy - lo[1], cx - lo[0]))
    x0, y0 = lo[0] + 0.8, lo[1] + 0.8
    map_poses = [camera_pose_from_base(x0 + dx, y0 - dx, yaw, 1.0, -15.0) for dx in (-0.2, 0.2)]
    T_query = look_at([x0 - 0.1, y0 - 0.1, 1.6], [cx, cy, 0.6])
    out = {"map": [], "query_T": T_query}
    for i, T in enumerate(map_poses):
        r = renderer.render(INTR, T)
        out["map"].append(MapKeyframe(r.rgb, INTR, T, r.depth_m, INTR, None, ("robot", i)))
    out["query_rgb"] = renderer.render(INTR, T_query).rgb
    return out


def test_registers_known_sim_camera(rendered: dict) -> None:
    est = register_view(View(rendered["query_rgb"], "cam0", INTR, None), rendered["map"])
    assert est.ok, est.reason
    assert est.inliers >= 30
    assert rotation_angle_deg(est.T_world_cam, rendered["query_T"]) < 1.0
    assert np.linalg.norm(est.T_world_cam[:3, 3] - rendered["query_T"][:3, 3]) < 0.05


def test_registers_without_intrinsics(rendered: dict) -> None:
    est = register_view(View(rendered["query_rgb"], "cam0", None, None), rendered["map"])
    assert est.ok, est.reason
    assert est.intrinsics is not None and abs(est.intrinsics.fx - INTR.fx) / INTR.fx < 0.05
    assert rotation_angle_deg(est.T_world_cam, rendered["query_T"]) < 2.0
    assert np.linalg.norm(est.T_world_cam[:3, 3] - rendered["query_T"][:3, 3]) < 0.15


def test_refuses_with_too_few_matches(rendered: dict) -> None:
    blank = np.full((480, 640, 3), 128, np.uint8)
    est = register_view(View(blank, "cam0", INTR, None), rendered["map"])
    assert not est.ok and "too few" in est.reason
    noise = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    est = register_view(View(noise, "cam0", INTR, None), rendered["map"])
    assert not est.ok and est.reason
    assert not register_view(View(blank, "cam0", INTR, None), []).ok


def test_two_view_pose_with_known_baseline(rendered: dict) -> None:
    a, b = rendered["map"]
    va = View(a.image, "robot", INTR, a.T_world_cam)
    vb = View(b.image, "robot", INTR, None)
    baseline = float(np.linalg.norm(a.T_world_cam[:3, 3] - b.T_world_cam[:3, 3]))
    est = two_view_pose(va, vb, baseline_m=baseline)
    assert est.ok, est.reason
    assert rotation_angle_deg(est.T_world_cam, b.T_world_cam) < 1.0
    assert np.linalg.norm(est.T_world_cam[:3, 3] - b.T_world_cam[:3, 3]) < 0.05
    assert not two_view_pose(va, vb).ok  # no scale source: refused with a reason


def test_two_view_pose_scale_from_camera_height(rendered: dict) -> None:
    # Robot keyframes 1.0 m above the floor: the floor is the dominant plane of the matched points.
    a, b = rendered["map"]
    va = View(a.image, "robot", INTR, a.T_world_cam)
    vb = View(b.image, "robot", INTR, None)
    est = two_view_pose(va, vb, camera_height_m=1.0)
    assert est.ok, est.reason
    baseline_true = float(np.linalg.norm(a.T_world_cam[:3, 3] - b.T_world_cam[:3, 3]))
    baseline_est = float(np.linalg.norm(a.T_world_cam[:3, 3] - est.T_world_cam[:3, 3]))
    assert abs(baseline_est - baseline_true) < 0.2 * baseline_true


def test_floor_distance_is_the_lowest_well_supported_band_along_up() -> None:
    from mapper.geometry.register import floor_distance

    rng = np.random.default_rng(0)
    up = np.array([0.0, -0.8, 0.6])  # a camera pitched down: world up in its frame
    up /= np.linalg.norm(up)
    side = np.cross(up, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)

    def layer(height: float, n: int) -> np.ndarray:
        a, b = rng.uniform(-2, 2, n), rng.uniform(-2, 2, n)
        return height * up + a[:, None] * np.array([1.0, 0.0, 0.0]) + b[:, None] * side

    floor, table = layer(-2.4, 400), layer(-1.65, 900)  # the table top holds more points than the floor
    strays = layer(-3.5, 5)
    X = np.concatenate([floor, table, strays]) + rng.normal(0, 0.005, (1305, 3))
    assert floor_distance(X, up) == pytest.approx(2.4, abs=0.03)
    assert floor_distance(X[:10], up) is None
