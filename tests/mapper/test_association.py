"""Mask association (mapper.association) and what fusion does with it: fragments of one object that estimated
depth scattered apart merge when one detection's mask holds them; neighbours with their own masks stay apart;
detections stereo gave no depth are placed by single-view geometry and join a similar node near them."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.association import KeyframeView, containment
from mapper.config import GeometryConfig, MapperCoreConfig, PerceptionConfig
from mapper.core import MapperCore
from mapper.fusion import FusionConfig, Object3D, ObjectMap, voxel_downsample
from mapper.geometry.contract import View
from mapper.geometry.singleview import depth_to_world
from mapper.perception.base import Detection, ViewGeometry, label_descriptor
from protocol.messages import Intrinsics
from protocol.poses import look_at
from tests.support.boxes import INTR, raycast
from tests.support.corner_camera import box, silhouette

TABLE = (np.array([1.0, -0.6, 0.0]), np.array([2.2, 0.6, 0.75]))
EYE = [-0.5, 0.0, 1.4]


def keyframe(boxes: list[tuple[np.ndarray, np.ndarray]], eye=EYE, target=(1.6, 0.0, 0.4)):
    """A keyframe of ray-cast boxes: its view, depth, per-box masks and per-box surface points."""
    T = look_at(eye, list(target))
    depth, idx = raycast(T, boxes)
    kv = KeyframeView(INTR.K(), T, np.where(np.isfinite(depth), depth, 0.0))
    pts = depth_to_world(np.where(np.isfinite(depth), depth, 0.0).astype(np.float32), INTR.K(), T)
    masks = [idx == k for k in range(len(boxes))]
    clouds = [voxel_downsample(pts[m], 0.03) for m in masks]
    return kv, masks, clouds


def test_a_cloud_inside_its_mask_is_contained_and_outside_another() -> None:
    other = (np.array([1.0, 1.0, 0.0]), np.array([1.5, 1.5, 0.5]))
    kv, masks, clouds = keyframe([TABLE, other])
    frac = containment(kv, clouds, masks)
    assert frac[0, 0] > 0.95 and frac[0, 1] < 0.05
    assert frac[1, 1] > 0.95 and frac[1, 0] < 0.05


def test_points_hidden_behind_the_keyframes_surface_do_not_count() -> None:
    kv, masks, clouds = keyframe([TABLE])
    behind = clouds[0] + 1.5 * kv.T_world_cam[:3, 2]  # 1.5 m farther along the view: behind the table's surface
    assert np.isnan(containment(kv, [behind], masks)[0, 0])
    unknown = KeyframeView(kv.K, kv.T_world_cam, np.zeros_like(kv.depth_m))  # no confident depth: cannot hide
    assert containment(unknown, [behind], masks)[0, 0] > 0.5


def fragments_and_whole(shift: float = 0.12):
    """Two halves of the table, each seen by one keyframe with depth off along x (no common points), and a
    third keyframe's detection of the whole table with its mask."""
    label = "table"
    desc = label_descriptor(label)
    kv, masks, clouds = keyframe([TABLE])
    whole = clouds[0]
    left = whole[whole[:, 1] < -0.05] + np.array([shift, 0.0, 0.0])
    right = whole[whole[:, 1] > 0.05] - np.array([shift, 0.0, 0.0])
    parts = [Object3D(p.astype(np.float32), label, 0.9, desc) for p in (left, right)]
    det = Object3D(whole.astype(np.float32), label, 0.9, desc, mask=masks[0])
    return parts, det, kv


def test_one_mask_merges_the_fragments_scattered_depth_made() -> None:
    parts, det, kv = fragments_and_whole()
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    for k, p in enumerate(parts):
        om.integrate([p], "robot1", k)
    assert len(om.nodes) == 2  # the halves share no points: 3D association keeps them apart
    res = om.integrate([det], "robot1", 2, kv)
    assert len(om.nodes) == 1 and res.merged_duplicates == 1
    [node] = om.nodes.values()
    assert node.observations == 3


def test_without_the_keyframe_the_fragments_stay_apart() -> None:
    """The same input judged in 3D only (the behaviour before mask association) keeps a fragment."""
    parts, det, kv = fragments_and_whole()
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    for k, p in enumerate(parts):
        om.integrate([p], "robot1", k)
    om.integrate([det], "robot1", 2)
    assert len(om.nodes) >= 2


def test_mask_association_can_be_switched_off() -> None:
    parts, det, kv = fragments_and_whole()
    om = ObjectMap(FusionConfig(merge_every_updates=100, mask_association=False))
    for k, p in enumerate(parts):
        om.integrate([p], "robot1", k)
    om.integrate([det], "robot1", 2, kv)
    assert len(om.nodes) >= 2


def test_neighbours_with_their_own_masks_stay_apart() -> None:
    """Two chairs 25 cm apart, each with its own mask in the keyframe: each detection joins its own node."""
    a = (np.array([1.2, -0.6, 0.0]), np.array([1.6, -0.2, 0.9]))
    b = (np.array([1.2, 0.05, 0.0]), np.array([1.6, 0.45, 0.9]))
    kv, masks, clouds = keyframe([a, b])
    desc = label_descriptor("chair")
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    om.integrate([Object3D(c.astype(np.float32), "chair", 0.9, desc) for c in clouds], "robot1", 0)
    assert len(om.nodes) == 2
    shifted = [Object3D((c + [0.1, 0.0, 0.0]).astype(np.float32), "chair", 0.9, desc, mask=m)
               for c, m in zip(clouds, masks, strict=True)]
    res = om.integrate(shifted, "robot1", 1, kv)
    assert len(om.nodes) == 2 and res.merged_duplicates == 0 and res.associated == 2


def test_a_coarse_guess_joins_a_similar_node_near_it_and_leaves_its_points() -> None:
    kv, masks, clouds = keyframe([TABLE])
    desc = label_descriptor("table")
    om = ObjectMap(FusionConfig(merge_every_updates=100))
    om.integrate([Object3D(clouds[0].astype(np.float32), "table", 0.9, desc)], "robot1", 0)
    [node] = om.nodes.values()
    before = node.points.copy()
    guess = Object3D((clouds[0] + [0.6, 0.0, 0.0]).astype(np.float32), "table", 0.9, desc,
                     ray_origin=np.array(EYE, float))
    res = om.integrate([guess], "robot1", 1, KeyframeView(kv.K, kv.T_world_cam, np.zeros_like(kv.depth_m)))
    assert res.created == 0 and len(om.nodes) == 1
    assert node.observations == 2 and np.array_equal(node.points, before)


@pytest.mark.parametrize(("mask_scale", "tol_m"), [(1, 0.15), (2, 0.2)])
def test_a_detection_stereo_gave_no_depth_is_placed_from_the_floor(mask_scale: int, tol_m: float) -> None:
    """The mapper's fallback for a textureless object: its mask's floor contact places it (within 15 cm), also
    from a mask at half the image's size, a little coarser (a worker's masks may come at the depth's size)."""
    intr = Intrinsics.from_fov(640, 480, 90.0)
    cam = look_at([0.2, 0.3, 1.2], [3.0, 2.5, 0.3])
    truth = box(2.6, 2.0, 0.0, 0.4, 0.4, 0.6)
    mask = silhouette(truth, cam)[::mask_scale, ::mask_scale]
    core = MapperCore(MapperCoreConfig(geometry=GeometryConfig(backend="oracle"),
                                       perception=PerceptionConfig(segmenter="sim", embedder="sim")))
    view = View(image=np.full((480, 640, 3), 120, np.uint8), source_id="robot1", intrinsics=intr, T_world_cam=cam,
                stamp_ns=1, seq=0)
    det = Detection(mask=mask, label="trash can", confidence=0.9, descriptor=label_descriptor("trash can"))
    none = np.zeros((240, 320), np.float32)
    [obj] = core._place_depthless(view, cam, [det], [0], ViewGeometry(np.zeros((240, 320, 3), np.float32), none, none))
    assert obj.ray_origin is not None
    assert np.linalg.norm(obj.points.mean(0)[:2] - truth.center[:2]) < tol_m
    assert obj.points[:, 2].max() == pytest.approx(0.6, abs=0.1)


def test_a_detection_without_depth_on_a_measured_table_top_stands_on_it() -> None:
    """A small object stereo gave no depth, on a table whose top has some: the keyframe's own depth under its
    mask is level at 0.75 m, so it is placed there (within 15 cm, like the floor placement), not on the floor and
    not dropped."""
    intr = Intrinsics.from_fov(640, 480, 90.0)
    cam = look_at([0.2, 0.3, 1.4], [2.6, 2.0, 0.75])
    truth = box(2.6, 2.0, 0.75, 0.2, 0.2, 0.25)
    table = box(2.6, 2.1, 0.0, 1.6, 1.0, 0.75)
    obj_mask, table_mask = silhouette(truth, cam), silhouette(table, cam)
    table_mask &= ~obj_mask
    small = intr.scaled(320, 240)
    vs, us = np.mgrid[0:240, 0:320].astype(float)
    rays = np.stack([(us - small.cx) / small.fx, (vs - small.cy) / small.fy, np.ones_like(us)], -1) @ cam[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = ((0.75 - cam[2, 3]) / rays[..., 2]).astype(np.float32)  # the table top's plane, camera z-depth
    on_top = table_mask[::2, ::2] & np.isfinite(depth) & (depth > 0)
    depth = np.where(on_top, depth, 0.0).astype(np.float32)
    vg = ViewGeometry(depth_to_world(depth, small.K(), cam), depth, on_top.astype(np.float32))
    core = MapperCore(MapperCoreConfig(geometry=GeometryConfig(backend="oracle"),
                                       perception=PerceptionConfig(segmenter="sim", embedder="sim")))
    core.config.single_view.measured_support = True
    view = View(image=np.full((480, 640, 3), 120, np.uint8), source_id="robot1", intrinsics=intr, T_world_cam=cam,
                stamp_ns=1, seq=0)
    dets = [Detection(mask=obj_mask, label="bowl", confidence=0.9, descriptor=label_descriptor("bowl")),
            Detection(mask=table_mask, label="table", confidence=0.9, descriptor=label_descriptor("table"))]
    [obj] = core._place_depthless(view, cam, dets, [0], vg)
    assert obj.ray_origin is not None and core.counters["detections_placed_on_measured_support"] == 1
    assert np.linalg.norm(obj.points.mean(0)[:2] - truth.center[:2]) < 0.15
    assert obj.points[:, 2].min() == pytest.approx(0.75, abs=0.1)  # on the table top, not the floor
    off = MapperCore(MapperCoreConfig(geometry=GeometryConfig(backend="oracle"),
                                      perception=PerceptionConfig(segmenter="sim", embedder="sim")))
    off.config.single_view.measured_support = False
    assert off._place_depthless(view, cam, dets, [0], vg) == []  # a guess on a guess (the table's box) is not kept
