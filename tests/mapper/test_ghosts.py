"""Ghost merging (mapper.fusion.ObjectMap.merge_ghosts): a keyframe whose estimated depth is wrong on an object
puts a copy of it nearer along its viewing rays. The copy's own keyframe hides the real node behind the wrong
depth (mask association does not count it) and the other views do not see the copy inside their masks, so
before ghost merging it stayed a duplicate node."""

from __future__ import annotations

import numpy as np

from mapper.association import KeyframeView
from mapper.fusion import FusionConfig, Object3D, ObjectMap, voxel_downsample
from mapper.geometry.singleview import depth_to_world
from mapper.perception.base import label_descriptor
from protocol.poses import look_at
from tests.support.boxes import INTR, raycast

VASE = (np.array([2.4, -0.1, 0.6]), np.array([2.6, 0.1, 0.9]))
OTHER_VASE = (np.array([1.6, -0.1, 1.0]), np.array([1.8, 0.1, 1.3]))  # nearer on nearly the same ray, higher
DESC = label_descriptor("vase")


def seen(eye: list[float], boxes: list[tuple[np.ndarray, np.ndarray]], depth_scale: float = 1.0,
         target=(2.5, 0.0, 0.75)) -> tuple[KeyframeView, list[Object3D]]:
    """A keyframe of ray-cast boxes whose depth is ``depth_scale`` times the truth (the same wrong depth in
    its view and in its detections' points), with one vase detection per visible box."""
    T = look_at(eye, list(target))
    depth, idx = raycast(T, boxes)
    depth = np.where(np.isfinite(depth), depth * depth_scale, 0.0)
    pts = depth_to_world(depth.astype(np.float32), INTR.K(), T)
    objs = []
    for k in range(len(boxes)):
        m = idx == k
        if m.sum() >= 5:
            objs.append(Object3D(voxel_downsample(pts[m], 0.03).astype(np.float32), "vase", 0.9, DESC, mask=m))
    return KeyframeView(INTR.K(), T, depth), objs


def well_seen_vase(om: ObjectMap) -> str:
    """The vase seen with true depth from two places: one node, two observations."""
    for k, eye in enumerate(([1.0, -1.5, 1.4], [1.0, 1.5, 1.4])):
        kv, objs = seen(eye, [VASE])
        om.integrate(objs, "robot1", k, kv)
    assert len(om.nodes) == 1
    return next(iter(om.nodes))


def test_a_copy_misplaced_along_its_rays_merges_into_the_better_seen_node() -> None:
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    host = well_seen_vase(om)
    before = om.nodes[host].points.copy()
    kv, objs = seen([0.0, 0.3, 1.4], [VASE], depth_scale=0.75)  # depth 25 % short: the copy is ~0.6 m nearer
    om.integrate(objs, "robot1", 2, kv)
    assert len(om.nodes) == 2  # neither point overlap nor the (hidden) mask association joined them
    res = om.maintain()
    assert res.merged_duplicates == 1 and list(om.nodes) == [host]
    node = om.nodes[host]
    assert node.observations == 3 and np.array_equal(node.points, before)  # the ghost's points are dropped


def test_ghost_merging_can_be_switched_off() -> None:
    om = ObjectMap(FusionConfig(merge_every_updates=100, ghost_merge=False))
    well_seen_vase(om)
    kv, objs = seen([0.0, 0.3, 1.4], [VASE], depth_scale=0.75)
    om.integrate(objs, "robot1", 2, kv)
    om.maintain()
    assert len(om.nodes) == 2


def test_two_objects_one_keyframe_showed_apart_stay_apart() -> None:
    """A second vase nearer on nearly the same ray, detected beside the first in one keyframe: not a ghost."""
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    host = well_seen_vase(om)
    kv, objs = seen([0.0, 0.0, 1.4], [VASE, OTHER_VASE], target=(2.5, 0.0, 0.9))
    assert len(objs) == 2
    om.integrate(objs, "robot1", 2, kv)
    assert len(om.nodes) == 2
    near = next(k for k in om.nodes if k != host)
    assert om.nodes[near].observations == 1
    om.maintain()
    assert len(om.nodes) == 2


def test_a_neighbour_beside_the_rays_is_not_a_ghost() -> None:
    """A vase 0.5 m to the side of the well seen one (across the ray, not along it) stays its own node."""
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    well_seen_vase(om)
    beside = (VASE[0] + [0.0, 0.5, 0.0], VASE[1] + [0.0, 0.5, 0.0])
    kv, objs = seen([0.0, 0.0, 1.4], [beside], target=(2.5, 0.5, 0.75))
    om.integrate(objs, "robot1", 2, kv)
    om.maintain()
    assert len(om.nodes) == 2


def test_a_node_seen_often_is_never_a_ghost() -> None:
    cfg = FusionConfig(merge_every_updates=100, ghost_max_observations=1)
    om = ObjectMap(cfg)
    host = well_seen_vase(om)
    kv, objs = seen([0.0, 0.3, 1.4], [VASE], depth_scale=0.75)
    om.integrate(objs, "robot1", 2, kv)
    om.integrate(objs, "robot1", 3, kv)  # the same wrong depth twice: two observations
    ghost = next(k for k in om.nodes if k != host)
    assert om.nodes[ghost].observations == 2
    assert om.ghost_host(om.nodes[ghost], om.nodes[host]) is None
    om.maintain()
    assert len(om.nodes) == 2


def test_the_host_keeps_its_own_sight_lines() -> None:
    """The ghost's rays led to where it was misplaced: the host does not take them (a later copy on those rays
    would otherwise count the host as the ghost)."""
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    host = well_seen_vase(om)
    before = [o.copy() for o, _ in om.nodes[host].sight]
    kv, objs = seen([0.0, 0.3, 1.4], [VASE], depth_scale=0.75)
    om.integrate(objs, "robot1", 2, kv)
    om.maintain()
    assert [o.tolist() for o, _ in om.nodes[host].sight] == [o.tolist() for o in before]
    assert len(om.nodes[host].seen_in) == 3  # what the keyframes told apart still counts


def test_a_far_object_at_half_its_depth_is_a_ghost_too() -> None:
    """Stereo depth errors grow with distance: a vase 5 m away came back at 55 % of its depth (2.2 m nearer,
    beyond ghost_max_along_m) and still merges (ghost_max_along_rel)."""
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    host = well_seen_vase(om)
    kv, objs = seen([-2.5, 0.0, 1.4], [VASE], depth_scale=0.55)
    om.integrate(objs, "robot1", 2, kv)
    assert len(om.nodes) == 2
    om.maintain()
    assert list(om.nodes) == [host]
    om2 = ObjectMap(FusionConfig(merge_every_updates=100, ghost_max_along_rel=0.2))
    well_seen_vase(om2)
    om2.integrate(objs, "robot1", 2, kv)
    om2.maintain()
    assert len(om2.nodes) == 2


def test_a_node_is_never_the_ghost_of_a_less_seen_one() -> None:
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    kv, objs = seen([1.0, -1.5, 1.4], [VASE])
    om.integrate(objs, "robot1", 0, kv)
    host = next(iter(om.nodes))
    kv, objs = seen([0.0, 0.3, 1.4], [VASE], depth_scale=0.75)
    om.integrate(objs, "robot1", 1, kv)
    om.integrate(objs, "robot1", 2, kv)
    ghost = next(k for k in om.nodes if k != host)
    assert om.ghost_host(om.nodes[ghost], om.nodes[host]) is None
    om.maintain()
    assert len(om.nodes) == 2


def test_a_coarse_guess_on_its_rays_through_a_measured_node_joins_it() -> None:
    """A single-view placement 2.5 m beyond the vase along its camera's ray (the floor contact misread) is the
    measured vase: it joins it, which keeps its points; one beside the ray stays."""
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    host = well_seen_vase(om)
    before = om.nodes[host].points.copy()
    eye = np.array([0.0, 0.3, 1.4])
    _, [obj] = seen(list(eye), [VASE])
    far = eye + (obj.points - eye) * 2.0  # twice as far along each pixel's ray
    guess = Object3D(far.astype(np.float32), "vase", 0.9, DESC, ray_origin=eye)
    om.integrate([guess], "cam1", 2)
    assert len(om.nodes) == 2
    om.maintain()
    assert list(om.nodes) == [host] and np.array_equal(om.nodes[host].points, before)
    beside = Object3D((far + [0.0, 1.0, 0.0]).astype(np.float32), "vase", 0.9, DESC, ray_origin=eye)
    om.integrate([beside], "cam1", 3)
    om.maintain()
    assert len(om.nodes) == 2


def test_sight_lines_and_keyframes_survive_a_restart() -> None:
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    host = well_seen_vase(om)
    kv, objs = seen([0.0, 0.3, 1.4], [VASE], depth_scale=0.75)
    om.integrate(objs, "robot1", 2, kv)
    back = ObjectMap(FusionConfig(merge_every_updates=100))
    back.load_state(om.state())
    for k, node in om.nodes.items():
        assert back.nodes[k].seen_in == node.seen_in
        assert np.allclose(np.array(back.nodes[k].sight), np.array(node.sight))
    back.maintain()
    assert list(back.nodes) == [host]  # the ghost is still known as one after the restart
    old = om.state()
    for d in old["nodes"]:
        del d["sight"], d["seen_in"]
    back.load_state(old)  # a state written before ghost merging loads
    assert all(not n.sight and not n.seen_in for n in back.nodes.values())
