"""Renderer: projection geometry, depth accuracy, determinism, backends."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from protocol.messages import Intrinsics, OrientedBox
from protocol.poses import invert, look_at, project
from sim.materials import make_material
from sim.render import Renderer
from sim.scene import Scene, SceneObject, generate_scene


def _box_scene(center: tuple[float, float, float], size: float) -> Scene:
    T = np.eye(4)
    T[:3, 3] = center
    mesh = trimesh.creation.box(extents=(size, size, size), transform=T)
    floor = trimesh.creation.box(extents=(40.0, 40.0, 0.1))
    floor.apply_translation((0.0, 0.0, -10.0))
    obj = SceneObject(obj_id=7, label="test box", category="test_box", room="lab", mesh=mesh,
                      box=OrientedBox(center=center, extent=(size, size, size)), parent_id=None,
                      centroid=np.array(center), face_material=np.zeros(12, np.int32))
    rng = np.random.default_rng(0)
    return Scene(family="test", seed=0, rooms=[], objects=[obj], relations=[], bounds_min=np.array([-20, -20, -10.1]),
                 bounds_max=np.array([20, 20, 5]), structure=floor, structure_face_material=np.zeros(12, np.int32),
                 materials=[make_material("wood", rng)])


@pytest.mark.parametrize("backend", ["embree", "open3d"])
def test_box_lands_at_projected_pixels_with_exact_depth(backend: str) -> None:
    center, size = (3.0, 0.4, 1.2), 1.0
    scene = _box_scene(center, size)
    K = Intrinsics(width=320, height=240, fx=200.0, fy=210.0, cx=161.3, cy=118.7)
    # camera at the origin-ish, looking along +x at the box's height: the front face is a plane x = 2.5
    T_world_cam = look_at((0.0, 0.1, 1.0), (3.0, 0.1, 1.0))
    out = Renderer(scene, backend=backend).render(K, T_world_cam)
    assert out.rgb.shape == (240, 320, 3) and out.rgb.dtype == np.uint8
    assert out.depth_m.dtype == np.float32 and out.instance_id.dtype == np.int32
    # projected rectangle of the front face
    corners = np.array([[2.5, center[1] + sy * 0.5, center[2] + sz * 0.5] for sy in (-1, 1) for sz in (-1, 1)])
    T_cam_world = invert(T_world_cam)
    pc = corners @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    uv, z = project(K.K(), pc)
    u0, u1 = uv[:, 0].min(), uv[:, 0].max()
    v0, v1 = uv[:, 1].min(), uv[:, 1].max()
    vv, uu = np.nonzero(out.instance_id == 7)
    assert abs(uu.min() - np.ceil(u0)) <= 1 and abs(uu.max() - np.floor(u1)) <= 1
    assert abs(vv.min() - np.ceil(v0)) <= 1 and abs(vv.max() - np.floor(v1)) <= 1
    # z-depth on the front face equals the known distance (camera x = 0, face at x = 2.5)
    inner = out.instance_id[int(v0) + 3:int(v1) - 3, int(u0) + 3:int(u1) - 3]
    assert (inner == 7).all()
    d = out.depth_m[int(v0) + 3:int(v1) - 3, int(u0) + 3:int(u1) - 3]
    assert np.abs(d - 2.5).max() < 1e-3
    # rays that miss everything: id -1, depth 0 (the top rows look over the box into empty space)
    assert (out.instance_id[0] == -1).all() and (out.depth_m[0] == 0).all()


def test_depth_is_z_not_range() -> None:
    scene = _box_scene((4.0, 0.0, 1.0), 1.0)
    scene.objects.clear()
    scene.__post_init__()
    wall = trimesh.creation.box(extents=(0.1, 30.0, 30.0))
    wall.apply_translation((5.05, 0.0, 0.0))
    scene.structure = wall
    K = Intrinsics.from_fov(64, 48, 90.0)
    out = Renderer(scene).render(K, look_at((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)))
    assert (out.instance_id == 0).all()
    assert np.abs(out.depth_m - 5.0).max() < 1e-4  # a fronto-parallel plane has constant z-depth


@pytest.fixture(scope="module")
def apt() -> Scene:
    return generate_scene("apartment", 3)


def test_renders_are_bit_identical_for_the_same_seed(apt: Scene) -> None:
    from sim.cameras import place_fixed_cameras

    cam = place_fixed_cameras(apt, 1, 0)[0]
    a = Renderer(apt).render(cam.intrinsics, cam.T_world_cam)
    b = Renderer(generate_scene("apartment", 3)).render(cam.intrinsics, cam.T_world_cam)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth_m, b.depth_m)
    assert np.array_equal(a.instance_id, b.instance_id)
    # a furnished view: several objects, textured (not flat) surfaces, structure visible
    ids = set(np.unique(a.instance_id).tolist())
    assert 0 in ids and len(ids - {0, -1}) >= 5
    floor = a.rgb[a.instance_id == 0].astype(float)
    assert floor.std(axis=0).mean() > 5.0
    c = Renderer(generate_scene("apartment", 4)).render(cam.intrinsics, cam.T_world_cam)
    assert not np.array_equal(a.rgb, c.rgb)


def test_backends_agree(apt: Scene) -> None:
    from sim.cameras import place_fixed_cameras

    cam = place_fixed_cameras(apt, 1, 1)[0]
    K = cam.intrinsics.scaled(160, 120)
    e = Renderer(apt, backend="embree").render(K, cam.T_world_cam)
    o = Renderer(apt, backend="open3d").render(K, cam.T_world_cam)
    assert (e.instance_id == o.instance_id).mean() > 0.99
    both = (e.depth_m > 0) & (o.depth_m > 0)
    assert np.median(np.abs(e.depth_m[both] - o.depth_m[both])) < 1e-4


def test_bad_pose_raises(apt: Scene) -> None:
    with pytest.raises(ValueError):
        Renderer(apt).render(Intrinsics.from_fov(32, 24, 90.0), np.full((4, 4), np.nan))
    with pytest.raises(ValueError):
        Renderer(apt, backend="optix")
