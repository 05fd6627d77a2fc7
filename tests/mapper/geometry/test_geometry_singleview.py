"""Single-view placement from the floor plane (mapper.geometry.singleview), the triangulation of coarse nodes
seen by several fixed cameras and the free-space check against other cameras (mapper.fusion.ObjectMap)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mapper.fusion import FusionConfig, Object3D, ObjectMap, UpdateResult, ray_meeting_point
from mapper.geometry.singleview import (
    SeenView,
    SingleViewParams,
    depth_to_world,
    layout_depth,
    pixel_rays,
    place_objects,
    ray_box_depth,
    relocate_along_ray,
)
from mapper.perception.base import label_descriptor
from protocol.poses import look_at
from tests.support.corner_camera import CAM, INTR, K, box, silhouette


@pytest.mark.parametrize("yaw_deg", [-20.0, 0.0, 45.0, 60.0])
def test_box_on_the_floor_is_placed_within_10_cm(yaw_deg: float) -> None:
    truth = box(3.0, 2.2, 0.0, 0.8, 0.5, 0.7, yaw_deg=yaw_deg)
    [placed] = place_objects([silhouette(truth)], K, CAM)
    assert placed is not None and placed.support == -1
    assert np.linalg.norm(placed.center - truth.center) < 0.10
    assert placed.extent[2] == pytest.approx(0.7, abs=0.1)
    assert sorted(placed.extent[:2]) == pytest.approx([0.5, 0.8], abs=0.15)


def test_box_with_one_visible_bottom_edge_gets_its_depth_from_the_silhouette() -> None:
    """At 30 deg yaw the box's long side recedes along the line of sight: only its short front edge touches
    the floor visibly, and the depth comes from fitting the silhouette (coarser than a corner view)."""
    truth = box(3.0, 2.2, 0.0, 0.8, 0.5, 0.7, yaw_deg=30.0)
    [placed] = place_objects([silhouette(truth)], K, CAM)
    assert placed is not None
    assert np.linalg.norm(placed.center - truth.center) < 0.2
    assert max(placed.extent[:2]) > 0.5  # deepened from the edge, not left flat


def test_object_on_a_table_rests_on_its_top() -> None:
    table = box(2.6, 2.0, 0.0, 1.2, 0.7, 0.75)
    vase = box(2.6, 2.0, 0.75, 0.15, 0.15, 0.3)
    vase_mask = silhouette(vase)
    table_mask = silhouette(table) & ~vase_mask
    placed_table, placed_vase = place_objects([table_mask, vase_mask], K, CAM)
    assert placed_table is not None and placed_vase is not None
    assert placed_vase.support == 0
    assert np.linalg.norm(placed_vase.center - vase.center) < 0.10
    # the drawn silhouettes are about a pixel fat: the table comes out a few centimetres tall
    assert placed_vase.center[2] - placed_vase.extent[2] / 2 == pytest.approx(0.75, abs=0.08)


def test_floor_seen_between_legs_does_not_push_the_object_back() -> None:
    """A table's top hides the floor contact in the columns between its legs: those columns see the floor
    behind it. Only the lower convex envelope (the legs) may place it."""
    legs = [box(2.6 + sx * 0.5, 2.0 + sy * 0.3, 0.0, 0.06, 0.06, 0.7) for sx in (-1, 1) for sy in (-1, 1)]
    top = box(2.6, 2.0, 0.7, 1.1, 0.7, 0.05)
    mask = silhouette(top)
    for leg in legs:
        mask |= silhouette(leg)
    [placed] = place_objects([mask], K, CAM)
    assert placed is not None
    assert np.linalg.norm(placed.center[:2] - [2.6, 2.0]) < 0.2


def test_masks_touching_nothing_or_cut_by_the_border_are_not_placed() -> None:
    picture = box(4.0, 3.5, 1.2, 0.6, 0.03, 0.4)  # hangs on a wall: the floor ray passes far behind it
    params = SingleViewParams(max_range_m=5.0)
    cut = np.zeros((INTR.height, INTR.width), bool)
    cut[300:, 100:200] = True  # runs off the bottom of the image
    assert place_objects([silhouette(picture), cut], K, CAM, params) == [None, None]
    assert place_objects([], K, CAM) == []


def test_layout_depth_puts_the_mask_on_the_box_surface() -> None:
    truth = box(3.0, 2.2, 0.0, 0.8, 0.5, 0.7, yaw_deg=30.0)
    mask = silhouette(truth)
    depth, conf = layout_depth([mask], [truth], K, CAM, confidence=0.4)
    assert np.all(depth[~mask] == 0) and np.all(conf[mask] == np.float32(0.4))
    pts = depth_to_world(depth, K, CAM)[mask]
    local = (pts - truth.center) @ truth.rotation()
    # every point lies on (or, for silhouette pixels that miss the box, near) the box
    assert np.mean(np.all(np.abs(local) <= truth.extent / 2 + 0.02, axis=1)) > 0.95


def test_ray_box_depth_hits_and_misses() -> None:
    b = box(0.0, 5.0, 0.0, 2.0, 2.0, 2.0)  # centre (0, 5, 1): faces at y = 4 and y = 6
    origin = np.array([0.0, 0.0, 1.0])
    d = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 1.0], [0.0, -1.0, 0.0]])
    s = ray_box_depth(origin, d, b)
    assert s[0] == pytest.approx(4.0)
    assert np.isnan(s[1]) and np.isnan(s[2])


def test_rays_meet_at_the_object() -> None:
    p = np.array([2.0, 1.0, 0.5])
    rays = []
    for o in (np.array([0.0, 0.0, 2.5]), np.array([5.0, 0.0, 2.5]), np.array([0.0, 4.0, 2.5])):
        rays.append((o, (p - o) / np.linalg.norm(p - o)))
    q, gap = ray_meeting_point(rays)
    assert np.allclose(q, p) and gap < 1e-9
    assert ray_meeting_point([rays[0], rays[0]])[1] == math.inf  # one direction fixes no depth


def _coarse(centre: np.ndarray, origin: np.ndarray, label: str) -> Object3D:
    rng = np.random.default_rng(0)
    pts = (centre + rng.uniform(-0.1, 0.1, (60, 3))).astype(np.float32)
    return Object3D(pts, label, 0.9, label_descriptor(label), ray_origin=origin)


def test_two_cameras_placements_of_one_object_merge_at_the_ray_crossing() -> None:
    """Each camera's single-view estimate is off in depth along its own ray; the merged node sits where the
    rays cross. Two vases 0.4 m apart stay two nodes; a chair is never merged with a vase."""
    a, b = np.array([0.0, 0.0, 2.5]), np.array([6.0, 0.0, 2.5])
    vase1, vase2, chair = np.array([2.5, 2.0, 0.6]), np.array([2.9, 2.2, 0.6]), np.array([3.0, 1.0, 0.4])

    def along(o: np.ndarray, p: np.ndarray, err: float) -> np.ndarray:
        return p + err * (p - o) / np.linalg.norm(p - o)

    om = ObjectMap(FusionConfig())
    om.integrate([_coarse(along(a, vase1, 0.5), a, "vase"), _coarse(along(a, vase2, -0.4), a, "vase"),
                  _coarse(along(a, chair, 0.3), a, "chair")], "cam0", 1)
    om.integrate([_coarse(along(b, vase1, -0.4), b, "vase"), _coarse(along(b, vase2, 0.5), b, "vase")], "cam1", 2)
    assert len(om.nodes) == 5
    chair_before = next(n for n in om.nodes.values() if "chair" in n.label_votes).points.copy()
    res = om.triangulate_coarse()
    assert res.merged_duplicates == 2 and len(om.nodes) == 3
    centres = sorted(n.points.mean(0).tolist() for n in om.nodes.values() if "vase" in n.label_votes)
    assert np.allclose(centres, sorted([vase1.tolist(), vase2.tolist()]), atol=0.03)
    chair_node = next(n for n in om.nodes.values() if "chair" in n.label_votes)
    assert np.array_equal(chair_node.points, chair_before)  # one camera: left where it was placed


def test_a_multi_view_observation_replaces_a_coarse_node() -> None:
    om = ObjectMap(FusionConfig())
    a = np.array([0.0, 0.0, 2.5])
    om.integrate([_coarse(np.array([2.0, 2.0, 0.5]), a, "vase")], "cam0", 1)
    [node] = om.nodes.values()
    assert len(node.rays) == 1
    stereo = Object3D(node.points + np.float32(0.05), "vase", 0.9, label_descriptor("vase"))  # 5 cm off
    om.integrate([stereo], "robot", 2)
    assert len(om.nodes) == 1 and node.rays == []
    assert np.array_equal(node.points, stereo.points)  # the measured points replace the coarse guess


def _room_image(T_world_cam: np.ndarray, floor_rgb: tuple[int, int, int] = (150, 110, 70),
                wall_rgb: tuple[int, int, int] = (90, 140, 90)) -> np.ndarray:
    """An image of an empty room: floor colour where the pixel's ray meets the floor within 5 m, wall beyond."""
    vs, us = np.mgrid[0:INTR.height, 0:INTR.width]
    rays = pixel_rays(K, us.reshape(-1).astype(float), vs.reshape(-1).astype(float)) @ T_world_cam[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -T_world_cam[2, 3] / rays[:, 2]
    foot = np.hypot(s * rays[:, 0], s * rays[:, 1])
    floor = ((s > 0) & (foot < 5.0)).reshape(INTR.height, INTR.width)
    img = np.empty((INTR.height, INTR.width, 3), np.uint8)
    img[floor], img[~floor] = floor_rgb, wall_rgb
    return img


def test_another_camera_moves_a_misplaced_object_to_where_it_saw_it() -> None:
    """Camera A placed the crate (a cabinet) 0.5 m too far along its ray. Camera B sees the crate where it really is and
    the floor (learnt under a chair it placed) where A put it: the node moves back along A's ray."""
    cam_b = look_at([0.3, 4.8, 2.5], [3.0, 2.0, 0.3])
    crate, chair = box(3.0, 2.2, 0.0, 0.5, 0.5, 1.0), box(2.0, 2.6, 0.0, 0.45, 0.45, 0.9)
    masks = [silhouette(crate, cam_b), silhouette(chair, cam_b) & ~silhouette(crate, cam_b)]
    seen = SeenView.build(_room_image(cam_b), masks, [label_descriptor("crate"), label_descriptor("chair")], K,
                          cam_b, floor_masks=[masks[1]])
    assert seen.floor.any() and not seen.floor[seen.owner >= 0].any()
    origin = CAM[:3, 3]
    misplaced = origin + 1.15 * (crate.center - origin)  # on A's ray, ~0.5 m too far, still above the floor
    rng = np.random.default_rng(1)
    pts = (misplaced + rng.uniform(-0.2, 0.2, (200, 3))).astype(np.float32)
    om = ObjectMap(FusionConfig())
    om.integrate([Object3D(pts, "crate", 0.9, label_descriptor("crate"), ray_origin=origin)], "cam_a", 1)
    n, free, same = seen.votes(pts.astype(np.float64), label_descriptor("crate"), 0.8)
    assert n > 100 and free > 0.6 * n and same < 0.3 * n  # what check_coarse calls refuted
    res = UpdateResult()
    assert om.check_coarse([seen], res) == 1
    [node] = om.nodes.values()
    assert res.changed == {node.node_id}
    assert np.linalg.norm(node.points.mean(0) - crate.center) < 0.15
    # a camera that saw nothing of the kind leaves the node where it is (a wall can look like the floor)
    far_again = ObjectMap(FusionConfig())
    far_again.integrate([Object3D(pts, "vase", 0.9, label_descriptor("vase"), ray_origin=origin)], "cam_a", 1)
    assert far_again.check_coarse([seen]) == 0
    assert np.allclose(next(iter(far_again.nodes.values())).points, pts)


def test_seen_view_takes_masks_at_another_resolution_than_the_image() -> None:
    """A segmenter may work at half size (the classical one does): the view is built as from full-size masks."""
    import cv2

    cam_b = look_at([0.3, 4.8, 2.5], [3.0, 2.0, 0.3])
    crate, chair = box(3.0, 2.2, 0.0, 0.5, 0.5, 1.0), box(2.0, 2.6, 0.0, 0.45, 0.45, 0.9)
    masks = [silhouette(crate, cam_b), silhouette(chair, cam_b) & ~silhouette(crate, cam_b)]
    half = [cv2.resize(m.astype(np.uint8), (m.shape[1] // 2, m.shape[0] // 2),
                       interpolation=cv2.INTER_NEAREST).astype(bool) for m in masks]
    full_back = [cv2.resize(m.astype(np.uint8), (m.shape[1] * 2, m.shape[0] * 2),
                            interpolation=cv2.INTER_NEAREST).astype(bool) for m in half]
    desc = [label_descriptor("crate"), label_descriptor("chair")]
    a = SeenView.build(_room_image(cam_b), half, desc, K, cam_b, floor_masks=[half[1]])
    b = SeenView.build(_room_image(cam_b), full_back, desc, K, cam_b, floor_masks=[full_back[1]])
    assert np.array_equal(a.owner, b.owner) and np.array_equal(a.floor, b.floor) and (a.owner >= 0).any()


def test_relocation_needs_agreement() -> None:
    seen_nothing = SeenView(K, CAM, np.full((2, 2), -1, np.int16), np.zeros((2, 2), bool),
                            np.zeros((0, 4), np.float32))
    pts = np.array([[3.0, 2.0, 0.5]] * 20)
    assert relocate_along_ray(pts, np.array([0.0, 0.0, 2.5]), label_descriptor("crate"), [seen_nothing], 0.8) is None


def test_relocation_never_puts_an_object_under_the_floor() -> None:
    """Camera B saw an object of the same kind where camera A's ray to the node goes on under the floor (another
    crate farther away, in line with that ray's continuation): the node is not moved there."""
    origin = CAM[:3, 3]
    rng = np.random.default_rng(2)
    pts = np.array([2.0, 1.6, 0.3]) + rng.uniform(-0.1, 0.1, (100, 3))
    ray = pts.mean(0) - origin
    under = origin + (origin[2] + 0.6) / -ray[2] * ray  # where the ray is 0.6 m under the floor
    cam_b = look_at([0.3, 4.8, 2.5], [2.5, 2.0, 0.0])
    pc = (under + (pts - pts.mean(0)) - cam_b[:3, 3]) @ cam_b[:3, :3]
    uv = pc[:, :2] / pc[:, 2:3] * np.diag(K)[:2] + K[:2, 2]
    owner = np.full((INTR.height, INTR.width), -1, np.int16)
    u0, v0 = np.floor(uv.min(0)).astype(int) - 2
    u1, v1 = np.ceil(uv.max(0)).astype(int) + 2
    assert 0 <= u0 < u1 < INTR.width and 0 <= v0 < v1 < INTR.height  # B sees where the ray goes under the floor
    owner[v0:v1, u0:u1] = 0
    seen = SeenView(K, cam_b, owner, np.zeros_like(owner, bool), label_descriptor("crate")[None].astype(np.float32))
    crate = label_descriptor("crate")
    anywhere = relocate_along_ray(pts, origin, crate, [seen], 0.8, below_floor_m=np.inf)
    assert anywhere is not None and (pts + anywhere)[:, 2].min() < -0.3  # what the search found before
    assert relocate_along_ray(pts, origin, crate, [seen], 0.8) is None


def test_an_object_seen_against_the_wall_is_not_pushed_through_it() -> None:
    """A TV on a wall bracket, 1 m above the floor: under it the camera sees the wall, and its floor ray
    would place it 8 m away. The floor under the other objects' feet looks different, so with the image the
    TV gets no floor placement; without it, it is placed far behind the wall."""
    tv = box(4.0, 3.2, 1.0, 1.0, 0.1, 0.6)
    floor_objects = [box(1.8, 1.6, 0.0, 0.5, 0.5, 0.5), box(2.4, 1.0, 0.0, 0.6, 0.4, 0.8),
                     box(1.2, 2.2, 0.0, 0.4, 0.4, 0.6)]
    masks = [silhouette(tv)]
    for b in floor_objects:
        masks.append(silhouette(b) & ~np.any(masks, axis=0))
    image = _room_image(CAM)
    blind = place_objects(masks, K, CAM)
    assert blind[0] is not None and np.linalg.norm(blind[0].center[:2] - tv.center[:2]) > 2.0
    seeing = place_objects(masks, K, CAM, image=image)
    assert seeing[0] is None
    assert all(b is not None and np.linalg.norm(b.center - t.center) < 0.15
               for b, t in zip(seeing[1:], floor_objects, strict=True))


def test_a_coarse_node_of_a_small_object_is_not_pruned_as_a_stray() -> None:
    """Nodes seen once with few points are dropped as noise after ``prune_after_updates``; a single-view
    placement of a small object (a cup: few points on its box) is a whole mask, not a stray, and stays."""
    cfg = FusionConfig()
    om = ObjectMap(cfg)
    rng = np.random.default_rng(2)
    few = lambda c: (np.asarray(c) + rng.uniform(-0.04, 0.04, (20, 3))).astype(np.float32)  # noqa: E731
    om.integrate([_coarse(np.array([2.0, 2.0, 0.8]), np.array([0.0, 0.0, 2.5]), "cup")], "cam", 1)
    om.nodes[next(iter(om.nodes))].points = few([2.0, 2.0, 0.8])
    om.integrate([Object3D(few([4.0, 1.0, 0.5]), "cup", 0.9, label_descriptor("cup"))], "robot", 2)
    for k in range(cfg.prune_after_updates + 1):
        om.integrate([], "robot", 3 + k)
    om.maintain()
    assert [bool(n.rays) for n in om.nodes.values()] == [True]


def test_an_object_taken_away_is_forgotten_by_the_camera_that_placed_it() -> None:
    """A fixed camera placed a crate and a chair; in its next keyframe the crate is gone and the floor shows
    where it stood: the crate's node goes (a removal to publish), the chair's stays."""
    crate, chair = box(3.0, 2.2, 0.0, 0.5, 0.5, 0.5), box(2.0, 1.4, 0.0, 0.45, 0.45, 0.9)
    image = _room_image(CAM)
    before = [silhouette(crate), silhouette(chair) & ~silhouette(crate)]
    boxes = place_objects(before, K, CAM, image=image)
    depth, conf = layout_depth(before, boxes, K, CAM)
    pts = depth_to_world(depth, K, CAM)
    om = ObjectMap(FusionConfig())
    objs = [Object3D(pts[m & (depth > 0)], lab, 0.9, label_descriptor(lab), ray_origin=CAM[:3, 3])
            for m, lab in zip(before, ("crate", "chair"), strict=True)]
    om.integrate(objs, "cam", 1)
    crate_id = next(i for i, n in om.nodes.items() if "crate" in n.label_votes)
    still = SeenView.build(image, before, [label_descriptor("crate"), label_descriptor("chair")], K, CAM,
                           floor_masks=before)
    assert om.forget_gone(still) == 0 and len(om.nodes) == 2  # both still there
    after = [silhouette(chair)]
    now = SeenView.build(image, after, [label_descriptor("chair")], K, CAM, floor_masks=after)
    res = UpdateResult()
    assert om.forget_gone(now, res) == 1
    assert res.removed == {crate_id} and [next(iter(n.label_votes)) for n in om.nodes.values()] == ["chair"]


def test_contact_subsets_keep_the_nearest_points() -> None:
    from mapper.geometry.singleview import _contact_subsets

    pts = np.array([[4.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [2.0, 0, 0]])
    subsets = _contact_subsets(pts, np.zeros(2), (1.0, 0.75, 0.5, 0.49), min_count=2)
    # 0.49 of 4 rounds to 2, the same size as 0.5: left out; sizes below min_count too
    assert [s[:, 0].tolist() for s in subsets] == [[1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0], [1.0, 2.0]]
    assert _contact_subsets(pts, np.zeros(2), (0.25,), min_count=2) == []


def test_floor_seen_past_an_objects_side_does_not_drop_it() -> None:
    """A cabinet against a wall: columns along its side see the floor far behind it (beyond the wall), so
    its contacts span more than ``max_extent_m``. The nearest contacts, whose box matches the silhouette,
    place it; with all contacts only (the old behaviour) it was dropped."""
    from mapper.geometry.singleview import _fit_box

    truth = box(3.0, 2.2, 0.0, 0.7, 0.6, 1.7)
    mask = silhouette(truth)
    lo, hi = truth.center[:2] - truth.extent[:2] / 2, truth.center[:2] + truth.extent[:2] / 2
    near_edges = np.concatenate([  # the two bottom edges that face the camera at (0.2, 0.3)
        np.stack([np.linspace(lo[0], hi[0], 30), np.full(30, lo[1]), np.zeros(30)], axis=1),
        np.stack([np.full(30, lo[0]), np.linspace(lo[1], hi[1], 30), np.zeros(30)], axis=1)])
    beyond = np.stack([np.full(12, hi[0] + 0.5), np.linspace(hi[1] + 2.0, hi[1] + 4.0, 12), np.zeros(12)], axis=1)
    pts = np.concatenate([near_edges, beyond])
    top_v = float(np.flatnonzero(mask.any(axis=1))[0]) - 0.5
    T_cam_world = np.linalg.inv(CAM)
    others = np.zeros_like(mask)
    args = (pts, -1, mask, others, top_v, K, T_cam_world, CAM[:3, 3])
    assert _fit_box(*args, SingleViewParams(trim_fractions=(1.0,))) is None
    placed = _fit_box(*args, SingleViewParams())
    assert placed is not None
    assert np.linalg.norm(placed.center - truth.center) < 0.1


def test_silhouette_fit_ignores_pixels_hidden_by_other_masks() -> None:
    from mapper.geometry.singleview import _SilhouetteFit

    truth = box(3.0, 2.2, 0.0, 1.2, 0.8, 0.75)
    front = silhouette(box(2.5, 1.2, 0.0, 0.3, 0.3, 0.9))
    mask = silhouette(truth) & ~front
    T_cam_world = np.linalg.inv(CAM)
    fit = _SilhouetteFit(mask, front, K, T_cam_world)
    assert fit.iou(truth) > 0.9  # the part behind the front object counts neither way
    assert _SilhouetteFit(mask, np.zeros_like(mask), K, T_cam_world).iou(truth) < fit.iou(truth)
    assert fit.iou(box(3.5, 2.2, 0.0, 1.2, 0.8, 0.75)) < 0.7
    assert fit.iou(box(3.0, 2.2, 0.0, 1.2, 0.8, 0.75, yaw_deg=180.0)) == pytest.approx(fit.iou(truth))


@pytest.mark.parametrize(("yaw_deg", "front_box"), [(0.0, (2.5, 1.2, 0.0, 0.3, 0.3, 0.9)),
                                                     (20.0, (2.6, 1.5, 0.0, 0.8, 0.3, 0.6))])
def test_an_object_whose_bottom_is_partly_hidden_is_refined_to_its_silhouette(
        yaw_deg: float, front_box: tuple[float, float, float, float, float, float]) -> None:
    """A table whose bottom edge is partly hidden by a stool in front: the contacts that remain leave its
    footprint short; fitting the box to the silhouette (the hidden pixels not counted) recovers it."""
    truth = box(3.0, 2.2, 0.0, 1.2, 0.8, 0.75, yaw_deg=yaw_deg)
    front = silhouette(box(*front_box))
    mask = silhouette(truth) & ~front
    coarse = place_objects([mask, front], K, CAM, SingleViewParams(refine_evals=0))[0]
    refined = place_objects([mask, front], K, CAM)[0]
    assert coarse is not None and refined is not None
    assert np.linalg.norm(coarse.center - truth.center) > 0.15
    assert np.linalg.norm(refined.center - truth.center) < 0.13


def test_floor_colour_tolerance_is_a_parameter() -> None:
    """Floor contacts keep their columns when the colour under them is within ``max_sigma`` robust standard
    deviations of the view's floor sample (an apartment camera sees several rooms' floors)."""
    from mapper.config import SingleViewConfig
    from mapper.geometry.singleview import _floor_looking

    rng = np.random.default_rng(0)
    image = np.zeros((20, 100, 3), np.uint8)
    image[:, :, :] = 120
    image[5, :, 0] = 120 + rng.integers(-6, 7, 100)  # the floor sample row (under the contacts' rows 2): noisy red
    lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(float)
    sd = np.clip(1.4826 * np.median(np.abs(lab[5] - np.median(lab[5], axis=0)), axis=0), 3.0, 15.0)
    mu = np.median(lab[5], axis=0)
    # one column whose colour under it lies about 4 sigmas from the floor's in some Lab channel
    for r in range(256):
        image[5, 99] = (r, 120, 120)
        z = float((np.abs(cv2.cvtColor(image[5:6, 99:100], cv2.COLOR_RGB2LAB).astype(float)[0, 0] - mu) / sd).max())
        if 3.6 < z < 4.4:
            break
    assert 3.6 < z < 4.4
    cols = [(np.arange(100, dtype=float), np.full(100, 2.0))]
    p = SingleViewParams()
    assert 99 not in _floor_looking(cols, image, p, max_sigma=3.0)[0][0]
    assert 99 in _floor_looking(cols, image, p, max_sigma=4.5)[0][0]
    assert SingleViewConfig(floor_colour_sigma=4.5).params().floor_colour_sigma == 4.5
    assert SingleViewConfig().params().floor_colour_sigma == 3.0


def test_two_floors_in_view_are_both_floor_and_a_wall_is_not() -> None:
    """An apartment camera sees its room's floor and, through a doorway, another room's: the floor sample is
    bimodal. Each colour cluster holding enough of it is a floor model of its own; a wall colour that is
    neither stays out, and a one-floor view keeps its one model's verdicts."""
    from mapper.geometry.singleview import _floor_looking, _floor_models, _two_means

    rng = np.random.default_rng(1)
    wood = np.array([150.0, 140.0, 170.0]) + rng.normal(0, 2, (60, 3))
    tiles = np.array([200.0, 135.0, 125.0]) + rng.normal(0, 2, (30, 3))
    labels = _two_means(np.concatenate([wood, tiles]))
    assert len(set(labels[:60])) == 1 and len(set(labels[60:])) == 1 and labels[0] != labels[60]
    assert len(_floor_models(np.concatenate([wood, tiles]), 0.3, 30)) == 3
    assert len(_floor_models(np.concatenate([wood, tiles]), 0.6, 30)) == 1  # off
    assert len(_floor_models(np.concatenate([wood, tiles[:10]]), 0.3, 30)) == 2  # 10 of 70: not a floor

    def image_of(under: list[tuple[int, int, int]]) -> np.ndarray:
        img = np.zeros((10, len(under), 3), np.uint8)
        img[5] = np.array(under, np.uint8)
        return img

    p = SingleViewParams()
    cols = [(np.arange(92, dtype=float), np.full(92, 2.0))]
    wood_rgb, tile_rgb, wall_rgb = (120, 90, 60), (200, 200, 205), (60, 80, 160)
    two = image_of([wood_rgb] * 60 + [tile_rgb] * 30 + [wall_rgb] * 2)
    two[5, :90] = np.clip(two[5, :90].astype(int) + rng.integers(-3, 4, (90, 3)), 0, 255).astype(np.uint8)
    kept = set(_floor_looking(cols, two, p)[0][0].astype(int).tolist())
    assert set(range(90)) <= kept and not {90, 91} & kept
    one_floor = SingleViewParams(floor_cluster_share=0.6)
    assert set(range(60)) <= set(_floor_looking(cols, two, one_floor)[0][0].astype(int).tolist())
    assert not set(range(60, 92)) & set(_floor_looking(cols, two, one_floor)[0][0].astype(int).tolist())


def _two_room_image(T_world_cam: np.ndarray) -> np.ndarray:
    """The camera's room floor (brown) within 5 m, another room's floor (pale blue tiles, seen through a doorway)
    from 5 to 8 m, a green wall beyond: each pixel by where its ray meets the floor plane."""
    vs, us = np.mgrid[0:INTR.height, 0:INTR.width]
    rays = pixel_rays(K, us.reshape(-1).astype(float), vs.reshape(-1).astype(float)) @ T_world_cam[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -T_world_cam[2, 3] / rays[:, 2]
    foot = np.where(s > 0, np.hypot(s * rays[:, 0], s * rays[:, 1]), np.inf).reshape(INTR.height, INTR.width)
    img = np.empty((INTR.height, INTR.width, 3), np.uint8)
    img[:] = (90, 140, 90)
    img[foot < 8.0] = (170, 190, 220)
    img[foot < 5.0] = (150, 110, 70)
    return img


def test_an_object_on_another_rooms_floor_is_placed_from_it() -> None:
    """A cabinet 6.5 m away stands on the floor of another room, which no nearer object stands on: its contacts
    fail the floor-colour test. What lies under it (tiles) is unlike what lies just above it (the wall), so it
    stands on a floor: it is placed from those contacts (``other_floor``), and left unplaced with it off. A TV
    on a wall bracket has the same wall above and below it and stays unplaced
    (``test_an_object_seen_against_the_wall_is_not_pushed_through_it``)."""
    from mapper.geometry.singleview import _other_floor

    d = np.array([2.8, 2.2]) / np.hypot(2.8, 2.2)  # the camera's horizontal viewing direction
    far = box(*(CAM[:2, 3] + 6.5 * d), 0.0, 0.5, 0.5, 0.9, yaw_deg=38.0)
    near = [box(1.8, 1.6, 0.0, 0.5, 0.5, 0.5), box(2.4, 1.0, 0.0, 0.6, 0.4, 0.8), box(1.2, 2.2, 0.0, 0.4, 0.4, 0.6)]
    masks = [silhouette(far)] + [silhouette(b) for b in near]
    image = _two_room_image(CAM)
    placed = place_objects(masks, K, CAM, image=image)
    assert placed[0] is not None and placed[0].support == -1
    assert np.linalg.norm(placed[0].center - far.center) < 0.25  # coarse at 6.5 m, well within a node match
    blind = place_objects(masks, K, CAM)[0]  # the same contacts as with no colour test at all
    assert blind is not None and np.allclose(placed[0].center, blind.center)
    assert all(b is not None and np.linalg.norm(b.center - t.center) < 0.15
               for b, t in zip(placed[1:], near, strict=True))
    assert place_objects(masks, K, CAM, SingleViewParams(other_floor=False), image=image)[0] is None
    # the same contacts with the tiles' colour above the object too: a surface behind it, not a floor under it
    cols = (np.arange(300.0, 310.0), np.full(10, 200.0))
    flat = np.full((INTR.height, INTR.width, 3), 200, np.uint8)
    mask = np.zeros((INTR.height, INTR.width), bool)
    mask[150:201, 300:310] = True
    owner = np.where(mask, 0, -1)
    empty = (cols[0][:0], cols[1][:0])
    assert _other_floor(cols, empty, mask, owner, flat, SingleViewParams()) == empty
    flat[:150] = (90, 140, 90)
    assert _other_floor(cols, empty, mask, owner, flat, SingleViewParams()) == cols


def test_an_object_behind_a_person_is_not_set_on_the_person() -> None:
    """From the camera high in the corner a passer-by hides a shelf's whole bottom edge: taken as one more mask,
    the person is a support and the shelf lands on the person's head, 1.3 m from where it stands; taken as an
    occluder, the person says nothing about the shelf, which is left to multi-view stereo."""
    person = silhouette(box(2.2, 1.7, 0.0, 0.45, 0.3, 1.7))
    shelf = box(3.0, 2.3, 0.0, 0.4, 0.3, 2.0)
    shelf_mask = silhouette(shelf) & ~person
    on_person, _ = place_objects([shelf_mask, person], K, CAM)
    assert on_person is not None and on_person.support == 1
    assert np.linalg.norm(on_person.center - shelf.center) > 1.0
    assert place_objects([shelf_mask], K, CAM, occluders=[person]) == [None]


def test_a_person_hiding_part_of_an_objects_floor_edge_leaves_it_placed_from_the_rest() -> None:
    truth = box(3.0, 2.2, 0.0, 1.2, 0.5, 0.7)
    person = silhouette(box(2.4, 1.7, 0.0, 0.45, 0.3, 1.7))
    mask = silhouette(truth) & ~person
    assert mask.sum() < silhouette(truth).sum()  # the person does hide part of it
    [placed] = place_objects([mask], K, CAM, occluders=[person])
    assert placed is not None and placed.support == -1
    assert np.linalg.norm(placed.center - truth.center) < 0.15
    with pytest.raises(ValueError, match="occluder"):
        place_objects([mask], K, CAM, occluders=[person[:-1]])
