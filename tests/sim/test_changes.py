"""Changing scenes and people: ground truth over time, renders that follow it, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from protocol.messages import Intrinsics, OrientedBox
from protocol.poses import invert, look_at
from sim.changes import (
    ChangingScene,
    Edit,
    add_edit,
    edits_from_spec,
    move_edit,
    random_edits,
    remove_edit,
)
from sim.materials import make_material
from sim.people import PERSON_ID_BASE, PERSON_LABEL, People, Walk, person_mesh
from sim.render import Renderer
from sim.scene import Room, Scene, SceneObject, generate_scene

K = Intrinsics(width=160, height=120, fx=100.0, fy=100.0, cx=80.0, cy=60.0)
CAM = look_at((0.0, 0.0, 1.0), (4.0, 0.0, 0.5))  # looks along +x from the origin, slightly down


def _room_scene() -> Scene:
    """A 10 m x 10 m floor (one room) with a 0.5 m box (id 3) 4 m in front of the camera."""
    floor = trimesh.creation.box(extents=(10.0, 10.0, 0.1))
    floor.apply_translation((2.0, 0.0, -0.05))
    T = np.eye(4)
    T[:3, 3] = (4.0, 0.0, 0.0)
    mesh = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    mesh.apply_translation((4.0, 0.0, 0.25))
    obj = SceneObject(obj_id=3, label="storage box", category="storage_box", room="hall", mesh=mesh,
                      box=OrientedBox(center=(4.0, 0.0, 0.25), extent=(0.5, 0.5, 0.5)), parent_id=None,
                      centroid=np.array([4.0, 0.0, 0.25]), T_world_obj=T, face_material=np.zeros(12, np.int32))
    rng = np.random.default_rng(0)
    return Scene(family="test", seed=0, rooms=[Room("hall", "living_room", np.array([-3.0, -5.0]),
                                                    np.array([7.0, 5.0]))],
                 objects=[obj], relations=[], bounds_min=np.array([-3.0, -5.0, -0.1]),
                 bounds_max=np.array([7.0, 5.0, 2.5]), structure=floor,
                 structure_face_material=np.zeros(len(floor.faces), np.int32), materials=[make_material("wood", rng)])


def _pixel(p_world: tuple[float, float, float]) -> tuple[int, int, float]:
    T = invert(CAM)
    pc = T[:3, :3] @ np.asarray(p_world) + T[:3, 3]
    return int(round(pc[1] / pc[2] * K.fy + K.cy)), int(round(pc[0] / pc[2] * K.fx + K.cx)), float(pc[2])


class TestScriptedEdits:
    def test_move_changes_truth_at_its_time_and_the_render_follows(self) -> None:
        scene = _room_scene()
        world = ChangingScene(scene, [move_edit(scene, 3, 5.0, (4.0, 1.5))])
        before, after = world.scene_at(4.99), world.scene_at(5.0)
        assert before is scene  # the generated scene itself until the edit
        assert np.allclose(after.object_by_id(3).box.center, (4.0, 1.5, 0.25))
        assert np.allclose(after.object_by_id(3).centroid, (4.0, 1.5, 0.25))
        assert np.allclose(np.asarray(after.object_by_id(3).mesh.vertices).mean(0)[:2], (4.0, 1.5))
        # the front face's middle: the box there before, the floor behind it after; the new place the other way
        old_v, old_u, _ = _pixel((3.75, 0.0, 0.25))
        new_v, new_u, z_new = _pixel((3.75, 1.5, 0.25))
        a, b = world.render(K, CAM, 4.0), world.render(K, CAM, 6.0)
        assert a.instance_id[old_v, old_u] == 3 and b.instance_id[old_v, old_u] == 0
        assert a.instance_id[new_v, new_u] == 0 and b.instance_id[new_v, new_u] == 3
        assert abs(float(b.depth_m[new_v, new_u]) - z_new) < 0.02
        assert not np.array_equal(a.rgb, b.rgb)

    def test_remove_and_add(self) -> None:
        scene = _room_scene()
        world = ChangingScene(scene, [remove_edit(scene, 3, 2.0),
                                      add_edit(scene, "backpack", 3.0, (3.0, -1.0), obj_id=4, seed=1)])
        assert [o.obj_id for o in world.objects_at(1.0)] == [3]
        assert world.objects_at(2.0) == []
        assert [o.obj_id for o in world.objects_at(3.0)] == [4]
        new = world.scene_at(3.0).object_by_id(4)
        assert new.label == "backpack" and new.room == "hall" and new.parent_id is None
        assert np.allclose(new.T_world_obj[:2, 3], (3.0, -1.0))
        assert float(np.asarray(new.mesh.vertices)[:, 2].min()) == pytest.approx(0.0, abs=1e-9)
        ids = world.render(K, CAM, 3.0).instance_id
        assert 4 in ids and 3 not in ids and 3 in world.render(K, CAM, 1.0).instance_id
        # the new object's materials come after the scene's, so the old objects' colours stay
        assert len(world.scene_at(0.0).materials) == 1 + len(world.edits[1].materials)
        assert world.next_id() == 5

    def test_spec_applies_in_time_order(self) -> None:
        scene = _room_scene()
        edits = edits_from_spec(scene, [{"t_s": 4.0, "kind": "remove", "obj_id": 3},
                                        {"t_s": 1.0, "kind": "move", "obj_id": 3, "to": [2.0, 2.0], "yaw_deg": 90},
                                        {"t_s": 6.0, "kind": "add", "category": "mug", "to": [1.0, 0.0]}])
        assert [e.kind for e in edits] == ["move", "remove", "add"]
        world = ChangingScene(scene, edits)
        assert math.isclose(world.scene_at(2.0).object_by_id(3).box.yaw_rad, math.pi / 2, abs_tol=1e-9)
        assert [o.label for o in world.objects_at(7.0)] == ["mug"]

    def test_bad_edits(self) -> None:
        scene = _room_scene()
        with pytest.raises(ValueError, match="kind"):
            Edit(t_s=1.0, kind="explode", obj_id=3)
        with pytest.raises(ValueError, match="object"):
            Edit(t_s=1.0, kind="move", obj_id=3)
        with pytest.raises(ValueError, match="not in the scene"):
            ChangingScene(scene, [Edit(t_s=1.0, kind="remove", obj_id=99)])
        with pytest.raises(ValueError, match="not in the scene"):  # removed twice
            ChangingScene(scene, [remove_edit(scene, 3, 1.0), remove_edit(scene, 3, 2.0)])


class TestPeople:
    def test_walk_is_piecewise_linear_and_holds_at_the_ends(self) -> None:
        w = Walk(PERSON_ID_BASE, np.array([1.0, 3.0, 4.0]), np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0]]))
        assert np.allclose(w.position(0.0), (0, 0)) and np.allclose(w.position(9.0), (2, 1))
        assert np.allclose(w.position(2.0), (1, 0)) and np.allclose(w.position(3.5), (2, 0.5))
        assert w.heading(2.0) == pytest.approx(0.0) and w.heading(3.5) == pytest.approx(math.pi / 2)

    def test_person_occludes_and_is_labelled_person(self) -> None:
        scene = _room_scene()
        # stands 2 m in front of the camera, between it and the box, for the whole episode
        people = People([Walk(PERSON_ID_BASE, np.array([0.0]), np.array([[2.0, 0.0]]))])
        world = ChangingScene(scene)
        plain, seen = world.render(K, CAM, 1.0), world.render(K, CAM, 1.0, people=people)
        v, u, _ = _pixel((3.75, 0.0, 0.25))
        assert plain.instance_id[v, u] == 3 and seen.instance_id[v, u] == PERSON_ID_BASE
        assert 1.75 < float(seen.depth_m[v, u]) < 2.2  # the person (2 m away, 0.2 m wide), nearer than the box (3.75 m)
        assert world.labels_at(1.0, people)[PERSON_ID_BASE] == PERSON_LABEL
        assert PERSON_LABEL not in world.scene_at(1.0).labels().values()  # never a ground-truth object
        # the ground truth does not change, and without people the frame is the plain scene's
        assert [o.obj_id for o in world.objects_at(1.0)] == [3]
        again = Renderer(scene).render(K, CAM)
        assert np.array_equal(again.rgb, plain.rgb) and np.array_equal(again.instance_id, plain.instance_id)

    def test_person_mesh_is_person_sized(self) -> None:
        mesh, part = person_mesh()
        lo, hi = np.asarray(mesh.vertices).min(0), np.asarray(mesh.vertices).max(0)
        assert lo[2] == pytest.approx(0.0) and 1.6 < hi[2] < 1.8 and 0.35 < hi[1] - lo[1] < 0.7
        assert set(np.unique(part)) == {0, 1} and len(part) == len(mesh.faces)


class TestGenerated:
    def test_random_edits_and_walks_are_deterministic_and_valid(self) -> None:
        from sim.nav import NavMap
        from sim.people import plan_walks

        scene = generate_scene("furnished_room", 1)
        a = random_edits(scene, 4, 40.0, seed=3)
        b = random_edits(scene, 4, 40.0, seed=3)
        assert [(e.kind, e.obj_id, round(e.t_s, 6)) for e in a] == [(e.kind, e.obj_id, round(e.t_s, 6)) for e in b]
        assert len(a) >= 3 and len({e.obj_id for e in a}) == len(a)
        assert all(0.2 * 40 <= e.t_s <= 0.75 * 40 for e in a)
        world = ChangingScene(scene, a)
        for e in a:
            after = {o.obj_id: o for o in world.scene_at(e.t_s).objects}
            before = {o.obj_id: o for o in world.scene_at(e.t_s - 1e-6).objects}
            if e.kind == "remove":
                assert e.obj_id in before and e.obj_id not in after
            elif e.kind == "add":
                assert e.obj_id not in before and e.obj_id in after
            else:
                moved = np.linalg.norm(np.subtract(after[e.obj_id].box.center, before[e.obj_id].box.center)[:2])
                assert moved >= 1.0
        nav = NavMap(scene)
        w1, w2 = plan_walks(nav, 2, 30.0, seed=5), plan_walks(nav, 2, 30.0, seed=5)
        for x, y in zip(w1, w2, strict=True):
            assert np.array_equal(x.xy, y.xy) and np.array_equal(x.times_s, y.times_s)
        for w in w1:
            assert w.times_s[-1] >= 20.0 and len({tuple(w.position(t)) for t in np.arange(0.0, 30.0, 1.0)}) > 10
            assert all(nav.is_free(*w.position(t)) or nav.snap(*w.position(t), 0.3) is not None
                       for t in np.arange(0.0, 30.0, 1.0))
