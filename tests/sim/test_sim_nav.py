"""Navigation, robot motion and odometry, fixed cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.messages import Intrinsics
from protocol.poses import invert, rotation_angle_deg
from sim.cameras import place_fixed_cameras, visible_objects
from sim.nav import NavMap, astar_cells
from sim.robot import OdometryNoise, SimRobot
from sim.scene import Scene, generate_scene


@pytest.fixture(scope="module")
def world() -> tuple[Scene, NavMap]:
    scene = generate_scene("apartment", 2)
    return scene, NavMap(scene)


def test_every_room_reachable_from_every_other(world: tuple[Scene, NavMap]) -> None:
    scene, nav = world
    reps = {}
    for r in scene.rooms:
        cells = nav.room_cells(r)
        assert len(cells) > 20, f"{r.name} has no reachable floor"
        reps[r.name] = cells[len(cells) // 2]
    names = list(reps)
    for a in names:
        for b in names:
            if a < b:
                assert nav.reachable(reps[a], reps[b])
                assert math.isfinite(nav.geodesic(reps[a], reps[b]))


def test_free_space_excludes_furniture_and_walls(world: tuple[Scene, NavMap]) -> None:
    scene, nav = world
    for o in scene.objects:
        if o.parent_id is None and o.box.extent[2] > 0.2:
            assert not nav.is_free(*o.box.center[:2]), o.label
    for d in scene.doors:  # doorways are passable
        assert nav.is_free(*d.center_xy)
    assert not nav.is_free(scene.bounds_min[0] - 1.0, 0.0)
    # free cells keep the robot radius away from obstacles
    from scipy import ndimage

    clearance = ndimage.distance_transform_edt(nav.floor) * nav.cell_m
    assert clearance[nav.free].min() > nav.robot_radius_m


def test_paths_are_free_and_shortest(world: tuple[Scene, NavMap]) -> None:
    scene, nav = world
    a = nav.room_cells(scene.rooms[0])[0]
    b = nav.room_cells(scene.rooms[-1])[-1]
    p = nav.path(a, b)
    assert p is not None and np.allclose(p[0], a) and np.allclose(p[-1], b)
    for k in range(len(p) - 1):
        assert nav._visible(p[k], p[k + 1])
    g = nav.geodesic(a, b)
    assert g >= np.linalg.norm(b - a) - 1e-9
    # the smoothed path is no longer than the 8-connected grid optimum (A* reference)
    cells = astar_cells(nav.free, nav.cell_of(*a), nav.cell_of(*b))
    assert cells is not None
    steps = np.diff(np.array(cells), axis=0)
    grid_len = float(np.sum(np.where(np.abs(steps).sum(1) == 2, math.sqrt(2), 1.0))) * nav.cell_m
    assert g <= grid_len + 2 * nav.cell_m
    field = nav.distances_from(a)
    assert abs(field(*b) - grid_len) < 0.1 * grid_len + 0.1
    assert nav.path(a, (scene.bounds_max[0] + 5.0, 0.0)) is None
    assert nav.geodesic(a, (scene.bounds_max[0] + 5.0, 0.0)) == math.inf


def test_viewpoints(world: tuple[Scene, NavMap]) -> None:
    scene, nav = world
    vps = nav.viewpoints(spacing_m=0.6, n_headings=8)
    assert len(vps) % 8 == 0 and len(vps) > 100
    assert [v.vp_id for v in vps] == list(range(len(vps)))
    assert all(nav.is_free(v.x, v.y) for v in vps)
    assert {v.room for v in vps} == {r.name for r in scene.rooms}
    vs = nav.viewpoint_set("r1", Intrinsics.from_fov(64, 48, 90.0))
    assert vs.robot_id == "r1" and len(vs.viewpoints) == len(vps)


def test_robot_exact_odometry_without_noise(world: tuple[Scene, NavMap]) -> None:
    scene, nav = world
    a = nav.room_cells(scene.rooms[0])[0]
    b = nav.room_cells(scene.rooms[-1])[-1]
    rob = SimRobot(scene, nav, (a[0], a[1], 0.3), Intrinsics.from_fov(80, 60, 90.0), noise=OdometryNoise.none())
    assert rob.drive_to(b[0], b[1], 1.0)
    assert rob.status == "moving"
    rob.step(3.0)  # turning in place first, then driving
    assert 0.0 < rob.distance_m <= 3.0 * rob.speed_mps + 1e-9
    assert rob.run_to_arrival() == "arrived"
    x, y, yaw = rob.pose_true()
    assert np.allclose([x, y], b) and abs(yaw - 1.0) < 1e-9
    assert rob.pose_odom() == rob.pose_true()
    assert np.array_equal(rob.T_world_cam_odom(), rob.T_world_cam_true())
    assert abs(rob.distance_m - nav.geodesic(a, b)) < 1e-6
    T = rob.T_world_cam_true()
    assert abs(T[2, 3] - 1.0) < 1e-12
    assert T[2, 2] < 0  # pitched down: the optical axis points below the horizon
    out = rob.render()
    assert out.rgb.shape == (60, 80, 3) and (out.instance_id >= 0).mean() > 0.9
    assert not rob.drive_to(scene.bounds_max[0] + 3.0, 0.0, 0.0) and rob.status == "refused"


def test_robot_odometry_drifts_with_noise(world: tuple[Scene, NavMap]) -> None:
    scene, nav = world
    a = nav.room_cells(scene.rooms[0])[0]
    b = nav.room_cells(scene.rooms[-1])[-1]
    errs = []
    for seed in range(2):
        rob = SimRobot(scene, nav, (a[0], a[1], 0.0), noise=OdometryNoise(0.05, 2.0, 1.0), seed=seed)
        rob.drive_to(b[0], b[1], 0.0)
        rob.step(4.0)
        e1 = np.hypot(*np.subtract(rob.pose_odom()[:2], rob.pose_true()[:2]))
        rob.run_to_arrival()
        e2 = np.hypot(*np.subtract(rob.pose_odom()[:2], rob.pose_true()[:2]))
        assert np.allclose(rob.pose_true()[:2], b)  # the true pose follows the path exactly
        errs.append((e1, e2, rob.pose_odom()))
        assert rotation_angle_deg(rob.T_world_cam_odom(), rob.T_world_cam_true()) > 0
    assert all(e2 > 0.01 for _, e2, _ in errs)
    assert errs[0][2] != errs[1][2]  # seeds give different drift
    rob2 = SimRobot(scene, nav, (a[0], a[1], 0.0), noise=OdometryNoise(0.05, 2.0, 1.0), seed=0)
    rob2.drive_to(b[0], b[1], 0.0)
    rob2.step(4.0)
    rob2.run_to_arrival()
    assert rob2.pose_odom() == errs[0][2]  # ... and the same seed the same drift


def test_odometry_covariance_grows_with_distance_and_turning(world: tuple[Scene, NavMap]) -> None:
    import math

    scene, nav = world
    a = nav.room_cells(scene.rooms[0])[0]
    rob = SimRobot(scene, nav, (a[0], a[1], 0.0), noise=OdometryNoise(0.05, 2.0, 1.0))
    c0 = rob.odometry_covariance()
    assert c0[0, 0] == 0.0 and c0[5, 5] == pytest.approx(1e-8)
    rob.drive_to(a[0], a[1], math.pi / 2)  # a quarter turn in place
    rob.run_to_arrival()
    c1 = rob.odometry_covariance()
    assert rob.turned_rad == pytest.approx(math.pi / 2)
    assert c1[0, 0] == 0.0  # no distance, no position drift
    assert c1[5, 5] - c0[5, 5] == pytest.approx(math.radians(1.0) ** 2 * math.pi / 2)


@pytest.mark.parametrize("family,n", [("apartment", 3), ("furnished_room", 3), ("apartment", 1)])
def test_fixed_cameras(family: str, n: int) -> None:
    scene = generate_scene(family, 5)
    cams = place_fixed_cameras(scene, n, seed=1, pose_known=[True] + [False] * (n - 1))
    assert len(cams) == n and len({c.camera_id for c in cams}) == n
    assert [c.pose_known for c in cams] == [True] + [False] * (n - 1)
    positions = [tuple(np.round(c.T_world_cam[:3, 3], 3)) for c in cams]
    assert len(set(positions)) == n
    for c in cams:
        room = next(r for r in scene.rooms if r.name == c.room)
        x, y, z = c.T_world_cam[:3, 3]
        assert room.contains(x, y) and z > 2.0 and z < scene.wall_height_m
        assert c.T_world_cam[2, 2] < -0.3  # looking down into the room
        assert np.allclose(invert(c.T_world_cam) @ c.T_world_cam, np.eye(4))
        assert len(visible_objects(scene, NavMap(scene).renderer, c.intrinsics, c.T_world_cam)) >= 3
    assert place_fixed_cameras(scene, n, seed=1)[0].T_world_cam.tolist() == cams[0].T_world_cam.tolist()
    with pytest.raises(ValueError):
        place_fixed_cameras(scene, 4, seed=0)
