"""Fixed cameras in the mapper: alone they make nodes (single-view floor geometry), two overlapping calibrated
cameras are a stereo pair, and a bumped camera is flagged (simulated room, ORACLE 2D perception)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.eval import fixed_camera_views, score
from bench.explore import core_config
from mapper.core import MapperCore
from mapper.geometry.contract import OracleData, View
from mapper.geometry.features import extract_features
from mapper.geometry.posecheck import rotation_between
from protocol.messages import Intrinsics
from protocol.poses import look_at
from sim.render import Renderer
from sim.scene import generate_scene

W, H = 480, 360


@pytest.fixture(scope="module")
def scene():  # type: ignore[no-untyped-def]
    return generate_scene("furnished_room", 3)


def _render(scene, T: np.ndarray, source: str, seq: int, pose: np.ndarray | None = None) -> View:  # type: ignore[no-untyped-def]
    intr = Intrinsics.from_fov(W, H, 90.0)
    out = Renderer(scene).render(intr, T)
    oracle = OracleData(depth_m=out.depth_m.astype(np.float32), T_world_cam_true=T,
                        instance_id=out.instance_id.astype(np.int32), labels=scene.labels())
    return View(out.rgb, source, intr, T if pose is None else pose, pose_trusted=True, stamp_ns=(seq + 1) * 10**9,
                seq=seq, oracle=oracle)


def _yawed(T: np.ndarray, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = T.copy()
    out[:3, :3] = Rz @ T[:3, :3]
    return out


def test_one_fixed_camera_alone_makes_nodes(scene) -> None:  # type: ignore[no-untyped-def]
    views = fixed_camera_views(scene, 1, 3, W, H)
    core = MapperCore(core_config("mvs", "sim"))
    for v in views:
        core.ingest(v, force_keyframe=True)
    s = score(core.nodes(), scene)
    assert core.counters["keyframes_single_view"] == 1
    assert s["recall"] > 0.3 and s["precision"] > 0.5


def test_rotation_between_measures_a_turn(scene) -> None:  # type: ignore[no-untyped-def]
    T = fixed_camera_views(scene, 1, 3, W, H)[0].oracle.T_world_cam_true  # type: ignore[union-attr]
    K = Intrinsics.from_fov(W, H, 90.0).K()
    ref = extract_features(_render(scene, T, "cam", 0).image)
    same = rotation_between(ref, extract_features(_render(scene, T, "cam", 1).image), K)
    turned = rotation_between(ref, extract_features(_render(scene, _yawed(T, 5.0), "cam", 2).image), K)
    assert same.rotation_deg is not None and same.rotation_deg < 0.2
    assert turned.rotation_deg == pytest.approx(5.0, abs=0.3)


def test_a_bumped_camera_is_flagged_and_not_fused(scene) -> None:  # type: ignore[no-untyped-def]
    T = fixed_camera_views(scene, 1, 3, W, H)[0].oracle.T_world_cam_true  # type: ignore[union-attr]
    core = MapperCore(core_config("mvs", "sim"))
    core.ingest(_render(scene, T, "cam0", 0), force_keyframe=True)
    nodes = {n.node_id: n.centroid for n in core.nodes()}
    assert nodes
    core.ingest(_render(scene, T, "cam0", 1), force_keyframe=True)  # unchanged: fine
    assert "camera_moved_deg.cam0" not in core.counters
    bumped = _render(scene, _yawed(T, 5.0), "cam0", 2, pose=T)  # turned 5 deg, still claims the surveyed pose
    core.ingest(bumped, force_keyframe=True)
    assert core.counters["camera_moved_deg.cam0"] == pytest.approx(5.0, abs=0.3)
    assert core.counters["keyframes_rejected_camera_moved"] == 1
    assert {n.node_id: n.centroid for n in core.nodes()} == nodes  # nothing else in the graph changed
    core.ingest(_render(scene, T, "cam0", 3), force_keyframe=True)  # put back: no longer flagged
    assert "camera_moved_deg.cam0" not in core.counters


def test_two_close_calibrated_cameras_are_a_stereo_pair(scene) -> None:  # type: ignore[no-untyped-def]
    """Two calibrated cameras 0.8 m apart on one wall see the room with parallax: multi-view stereo gives
    their depth (AbsRel <= 0.10 where confident), not just the single-view floor geometry."""
    target = np.array([3.0, 2.5, 0.6])
    views = [_render(scene, look_at([0.6 + dx, 0.25, 2.3], target), f"cam{i}", 0)
             for i, dx in enumerate((0.0, 0.8))]
    core = MapperCore(core_config("mvs", "sim"))
    core.ingest(views[0], force_keyframe=True)
    core.ingest(views[1], force_keyframe=True)
    # cam0 alone: single-view; cam1: stereo with cam0; then cam0 is retried with cam1 as its partner
    assert core.counters["keyframes_single_view"] == 1 and core.counters["keyframes"] == 2
    last = core.last
    assert last is not None and last.view.source_id == "cam0"
    d, c = last.geometry.depth_m, last.geometry.confidence
    true = views[0].oracle.depth_m  # type: ignore[union-attr]
    if true.shape != d.shape:
        import cv2

        true = cv2.resize(true, (d.shape[1], d.shape[0]), interpolation=cv2.INTER_NEAREST)
    ok = (c >= 0.5) & (d > 0) & (true > 0)
    assert ok.mean() > 0.2
    assert float(np.median(np.abs(d[ok] - true[ok]) / true[ok])) <= 0.10


def test_a_retried_old_view_does_not_unflag_a_bumped_camera(scene) -> None:  # type: ignore[no-untyped-def]
    """cam0's first keyframe waits for a stereo partner; cam0 is then bumped and flagged. When cam1 (0.8 m
    away) arrives, cam0's old keyframe is reconstructed with it, but the camera stays flagged: that image was
    taken before it moved."""
    target = np.array([3.0, 2.5, 0.6])
    T0 = look_at([0.6, 0.25, 2.3], target)
    core = MapperCore(core_config("mvs", "sim"))
    core.ingest(_render(scene, T0, "cam0", 0), force_keyframe=True)
    core.ingest(_render(scene, _yawed(T0, 5.0), "cam0", 1, pose=T0), force_keyframe=True)
    assert "camera_moved_deg.cam0" in core.counters
    core.ingest(_render(scene, look_at([1.4, 0.25, 2.3], target), "cam1", 0), force_keyframe=True)
    assert core.last is not None and core.last.view.source_id == "cam0"  # the old keyframe was retried
    assert "camera_moved_deg.cam0" in core.counters


def _with_person(scene, T: np.ndarray, source: str, seq: int, xy: np.ndarray) -> View:  # type: ignore[no-untyped-def]
    from sim.people import PERSON_ID_BASE, People, Walk

    people = People([Walk(PERSON_ID_BASE, np.array([0.0]), np.asarray([xy], float))])
    intr = Intrinsics.from_fov(W, H, 90.0)
    out = Renderer(scene).render(intr, T, overlay=people.layer(0.0))
    oracle = OracleData(depth_m=out.depth_m.astype(np.float32), T_world_cam_true=T,
                        instance_id=out.instance_id.astype(np.int32), labels={**scene.labels(), **people.labels()})
    return View(out.rgb, source, intr, T, pose_trusted=True, stamp_ns=(seq + 1) * 10**9, seq=seq, oracle=oracle)


@pytest.mark.parametrize("changed_only", [True, False])
def test_a_passer_by_makes_a_lone_fixed_camera_place_nothing_again(scene, changed_only: bool) -> None:  # type: ignore[no-untyped-def]
    """A person walks into a lone fixed camera's view: its next keyframe (single-view, no stereo partner) places
    nothing again (``single_view.changed_only``); without the rule it placed every object again, those the
    person cuts included."""
    T = fixed_camera_views(scene, 1, 3, W, H)[0].oracle.T_world_cam_true  # type: ignore[union-attr]
    cfg = core_config("mvs", "sim")
    cfg.single_view.changed_only = changed_only
    core = MapperCore(cfg)
    core.ingest(_render(scene, T, "cam0", 0), force_keyframe=True)
    before = {n.node_id: n.box for n in core.nodes()}
    assert len(before) >= 5
    ahead = T[:3, 3] + 2.5 * T[:3, 2]
    for seq, side in enumerate((-0.4, 0.0, 0.4), start=1):  # walking across the view, 2.5 m from the camera
        xy = ahead[:2] + side * np.array([T[1, 0], -T[0, 0]]) / max(1e-9, float(np.hypot(T[0, 0], T[1, 0])))
        core.ingest(_with_person(scene, T, "cam0", seq, xy), force_keyframe=True)
    assert core.counters["keyframes_single_view"] == 4 and core.counters["detections_people"] >= 3
    after = {n.node_id: n.box for n in core.nodes()}
    if changed_only:
        assert core.counters["single_view_placed"] == len(before)  # the first keyframe's objects only
        assert core.counters["single_view_unchanged"] >= 3 * (len(before) - 2)
        assert after == before
    else:
        assert core.counters["single_view_placed"] >= 3 * (len(before) - 2)
        assert after != before


def test_a_passer_by_leaves_no_points_in_the_map(scene) -> None:  # type: ignore[no-untyped-def]
    """Measured depth (true geometry here) of a person's pixels is not added to the point map."""
    T = fixed_camera_views(scene, 1, 3, W, H)[0].oracle.T_world_cam_true  # type: ignore[union-attr]
    xy = (T[:3, 3] + 2.5 * T[:3, 2])[:2]
    core = MapperCore(core_config("oracle", "sim"))
    core.ingest(_with_person(scene, T, "cam0", 0, xy), force_keyframe=True)
    assert core.counters["detections_people"] == 1
    pts = core.voxels.points()
    near = (np.hypot(pts[:, 0] - xy[0], pts[:, 1] - xy[1]) < 0.3) & (pts[:, 2] > 0.3) & (pts[:, 2] < 1.6)
    assert len(pts) > 1000 and int(near.sum()) == 0
