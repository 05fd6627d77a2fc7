"""3D fusion on hand-made data: a tiny analytic ray caster of axis-aligned boxes stands in for geometry."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.fusion import (
    FusionConfig,
    Object3D,
    ObjectMap,
    dbscan_labels,
    densest_interval,
    fit_box,
    lift_detections,
    main_cluster,
    outside_fraction,
    voxel_downsample,
)
from mapper.perception.base import Detection, label_descriptor
from protocol.poses import look_at
from tests.support.boxes import raycast, world_points


def book_points(rng: np.random.Generator, x0: float) -> np.ndarray:
    """300 points of a 4 cm wide book standing on a shelf, its spine from ``x0``."""
    return np.column_stack([rng.uniform(x0, x0 + 0.04, 300), rng.uniform(2.0, 2.2, 300),
                            rng.uniform(1.0, 1.25, 300)]).astype(np.float32)


def detections(idx: np.ndarray, labels: list[str]) -> list[Detection]:
    out = []
    for k, lab in enumerate(labels):
        m = idx == k
        if m.any():
            out.append(Detection(mask=m, label=lab, confidence=0.9, descriptor=label_descriptor(lab)))
    return out


def observe(omap: ObjectMap, T: np.ndarray, boxes, labels, source="cam0", stamp=1):
    depth, idx = raycast(T, boxes)
    objs, stats = lift_detections(
        detections(idx, labels), world_points(T, depth), np.ones_like(depth), depth, omap.cfg
    )
    return omap.integrate(objs, source, stamp), stats


CHAIR = (np.array([0.0, 0.0, 0.0]), np.array([0.5, 0.5, 0.9]))
CHAIR2 = (np.array([0.56, 0.0, 0.0]), np.array([1.06, 0.5, 0.9]))  # 6 cm beside the first


class TestHelpers:
    def test_voxel_downsample(self) -> None:
        pts = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.5, 0.5, 0.5]], dtype=np.float32)
        out = voxel_downsample(pts, 0.1)
        assert len(out) == 2
        assert np.allclose(sorted(out[:, 0]), [0.015, 0.5])
        assert len(voxel_downsample(np.zeros((0, 3)), 0.1)) == 0

    def test_dbscan_keeps_main_cluster(self) -> None:
        rng = np.random.default_rng(0)
        blob = rng.normal(0, 0.02, (200, 3))
        small = rng.normal(1.0, 0.02, (20, 3))
        outlier = np.array([[5.0, 5.0, 5.0]])
        pts = np.concatenate([blob, small, outlier])
        labels = dbscan_labels(pts, 0.1, 4)
        assert labels[-1] == -1
        assert len(set(labels[:200])) == 1 and len(set(labels[200:220])) == 1 and labels[0] != labels[200]
        assert len(main_cluster(pts, 0.1, 4)) == 200
        assert len(main_cluster(np.zeros((0, 3)), 0.1, 4)) == 0

    def test_compiled_dbscan_equals_sparse_components(self) -> None:
        from scipy.spatial import cKDTree

        from mapper import fusion

        if fusion._dbscan_compiled is None:
            pytest.skip("numba not installed")
        rng = np.random.default_rng(5)
        for k in range(200):
            # sparse clouds of a few clumps: many border points between clusters, noise and single points
            n = int(rng.integers(0, 120))
            pts = rng.normal(0, 0.3, (n, 3)) + rng.integers(0, 3, (n, 1)) * 0.5
            eps, min_samples = float(rng.uniform(0.05, 0.3)), int(rng.integers(1, 8))
            pairs = cKDTree(pts).query_pairs(eps, output_type="ndarray")
            want = fusion._dbscan_from_pairs(pairs, n, min_samples)
            assert np.array_equal(dbscan_labels(pts, eps, min_samples), want), k

    def test_overlap_fraction_equals_full_search(self) -> None:
        from scipy.spatial import cKDTree

        from mapper.fusion import NodeState, overlap_fraction

        rng = np.random.default_rng(6)
        for k in range(100):
            node_pts = rng.uniform(0, 0.5, (int(rng.integers(1, 300)), 3)).astype(np.float32)
            pts = (rng.uniform(-0.3, 0.8, (int(rng.integers(1, 300)), 3))).astype(np.float32)
            if k % 4 == 0:  # points at exactly the radius from node points, along an axis
                m = min(len(pts), len(node_pts))
                pts[:m] = node_pts[:m] + np.float32(0.0625) * np.eye(3, dtype=np.float32)[k % 3]
            node = NodeState("n", node_pts, np.ones(4), 1, {}, set(), 0, 0, 0)
            r = 0.0625
            d, _ = cKDTree(node_pts).query(pts, k=1, distance_upper_bound=r)
            assert overlap_fraction(pts, node, r) == float(np.mean(d <= r)), k

    def test_fit_box_rotated(self) -> None:
        rng = np.random.default_rng(1)
        local = rng.uniform([-1.0, -0.25, 0.0], [1.0, 0.25, 0.5], (2000, 3))
        yaw = 0.3
        c, s = np.cos(yaw), np.sin(yaw)
        pts = local @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [2.0, 1.0, 0.0]
        b = fit_box(pts)
        assert b.yaw_rad == pytest.approx(yaw, abs=0.03)
        assert b.extent[0] == pytest.approx(2.0, abs=0.05) and b.extent[1] == pytest.approx(0.5, abs=0.05)
        assert b.center == pytest.approx((2.0, 1.0, 0.25), abs=0.03)

    def test_fit_box_trim_ignores_strays(self) -> None:
        rng = np.random.default_rng(2)
        pts = rng.uniform([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], (1000, 3))
        strays = np.array([[4.0, 0.5, 0.5], [0.5, -3.0, 0.5], [0.5, 0.5, 3.0]])
        loose, robust = fit_box(np.vstack([pts, strays])), fit_box(np.vstack([pts, strays]), trim=0.02)
        assert max(loose.extent) > 3.0
        assert robust.extent == pytest.approx((1.0, 1.0, 1.0), abs=0.1)
        assert robust.center == pytest.approx((0.5, 0.5, 0.5), abs=0.05)

    def test_node_box_trimmed_but_merging_sees_all_points(self) -> None:
        rng = np.random.default_rng(3)
        pts = np.vstack([rng.uniform(0.0, 1.0, (2000, 3)), [[3.0, 0.5, 0.5]]]).astype(np.float32)
        omap = ObjectMap(FusionConfig(box_trim_fraction=0.005))
        node = omap._new_node(Object3D(pts, "chair", 0.9, label_descriptor("chair")), "cam0", 1)
        assert node.box.extent[0] == pytest.approx(1.0, abs=0.05)
        assert max(node.full_box.extent[:2]) > 2.5

    def test_detection_with_sparse_depth_is_dropped(self) -> None:
        T = look_at([2.0, -1.5, 1.5], [0.25, 0.25, 0.45])
        depth, idx = raycast(T, [CHAIR])
        dets = detections(idx, ["chair"])
        conf = np.zeros_like(depth)
        ys, xs = np.nonzero(idx == 0)
        pick = np.arange(0, len(ys), 12)  # confident depth on ~8 % of the mask
        conf[ys[pick], xs[pick]] = 1.0
        cfg = FusionConfig(min_points=5, min_object_points=3, dbscan_min_samples=1, dbscan_eps_m=0.5)
        objs, stats = lift_detections(dets, world_points(T, depth), conf, depth, cfg)
        assert objs == [] and stats.dropped_no_depth == 1
        cfg = cfg.model_copy(update={"min_depth_fraction": 0.05})
        objs, _ = lift_detections(dets, world_points(T, depth), conf, depth, cfg)
        assert len(objs) == 1

    def test_object_whose_depth_comes_in_parts_is_lifted_whole(self) -> None:
        # Estimated depth on a textureless table top is its two textured ends, 15 cm apart: both are the table.
        # A layer 0.6 m behind (depth bled in from the wall) is still left out.
        h, w = 40, 60
        xs = np.linspace(0.0, 0.75, w)
        pw = np.zeros((h, w, 3), np.float32)
        pw[..., 0] = xs[None, :]
        pw[..., 1] = np.linspace(2.0, 2.3, h)[:, None]
        pw[..., 2] = 0.75
        conf = np.ones((h, w), np.float32)
        conf[:, (xs > 0.3) & (xs < 0.45)] = 0.0  # the textureless middle
        pw[30:, 50:, 1] += 0.6  # the wall's depth in one corner of the mask
        depth = pw[..., 1].copy()
        det = Detection(mask=np.ones((h, w), bool), label="table", confidence=0.9,
                        descriptor=label_descriptor("table"))
        (obj,), _ = lift_detections([det], pw, conf, depth, FusionConfig())
        assert obj.points[:, 0].min() < 0.05 and obj.points[:, 0].max() > 0.7
        assert obj.points[:, 1].max() < 2.35

    def test_one_surface_estimated_a_few_cm_apart_is_one_node(self) -> None:
        # Two keyframes' estimated depth of one side of a dresser, 4 cm apart along the view: one object.
        rng = np.random.default_rng(4)
        side = np.column_stack([rng.uniform(0, 0.8, 400), np.full(400, 2.0), rng.uniform(0, 0.8, 400)])
        omap = ObjectMap(FusionConfig())
        for k, dy in enumerate((0.0, 0.04)):
            pts = (side + [0.0, dy, 0.0]).astype(np.float32)
            omap.integrate([Object3D(pts, "dresser", 0.9, label_descriptor("dresser"))], "robot0", k + 1)
        assert len(omap.nodes) == 1

    def test_densest_interval(self) -> None:
        vals = np.array([1.0, 2.0, 2.1, 2.2, 2.25, 4.0, 4.1])
        assert densest_interval(vals, 0.3) == pytest.approx((2.0, 2.3))
        assert densest_interval(np.array([3.0, 1.0]), 0.5) == pytest.approx((1.0, 1.5))  # a tie: the nearest

    def test_depth_smeared_through_a_thin_object_is_cut_at_its_size(self) -> None:
        # A 10 cm pole 2 m away; a third of its pixels got depth smeared from the pole to the wall 3 m behind it.
        h, w, f = 60, 8, 100.0  # the mask is 60 px tall: 1.2 m at 2 m
        depth = np.full((h, w), 2.0, np.float32)
        depth[40:, :] = np.linspace(2.0, 5.0, 20)[:, None]
        v, u = np.mgrid[0:h, 0:w].astype(np.float32)
        pw = np.stack([(u - w / 2) / f * depth, depth, (h / 2 - v) / f * depth + 1.0], -1)
        det = Detection(mask=np.ones((h, w), bool), label="floor lamp", confidence=0.9,
                        descriptor=label_descriptor("floor lamp"))
        cfg = FusionConfig(min_object_points=3, dbscan_min_samples=1, voxel_m=0.01)
        (smeared,), _ = lift_detections([det], pw, np.ones((h, w), np.float32), depth, cfg)
        assert smeared.points[:, 1].max() > 4.0
        cut = cfg.model_copy(update={"depth_window_rel": 0.5, "depth_window_min_m": 0.3})
        (obj,), _ = lift_detections([det], pw, np.ones((h, w), np.float32), depth, cut, focal_px=f)
        assert obj.points[:, 1].min() >= 2.0 - 1e-6 and obj.points[:, 1].max() <= 2.0 + 0.6 + 1e-6
        assert len(obj.points) >= 40 * w * 0.5  # the pole itself is kept
        # Without the focal length (size unknown) nothing is cut.
        (same,), _ = lift_detections([det], pw, np.ones((h, w), np.float32), depth, cut)
        assert same.points[:, 1].max() > 4.0

    def test_outside_fraction_flags_depth_under_the_floor(self) -> None:
        cfg = FusionConfig()
        T = look_at([0.0, -2.0, 1.0], [0.0, 0.0, 0.3])
        floor = (np.array([-20.0, -20.0, -0.05]), np.array([20.0, 20.0, 0.0]))
        depth, _ = raycast(T, [floor, CHAIR])
        conf = (depth > 0).astype(np.float32)
        assert outside_fraction(world_points(T, depth), conf, depth, cfg) < 0.05
        far = depth * 3.0  # a scale failure: the floor seen three times too far lies under it
        assert outside_fraction(world_points(T, far), conf, far, cfg) > 0.5
        assert outside_fraction(world_points(T, far), np.zeros_like(conf), far, cfg) == 0.0


class TestFusion:
    def test_same_object_two_views_merges(self) -> None:
        omap = ObjectMap(FusionConfig())
        r1, _ = observe(omap, look_at([2.0, -1.5, 1.5], [0.25, 0.25, 0.45]), [CHAIR], ["chair"], "cam0", 10)
        r2, _ = observe(omap, look_at([-1.5, -1.2, 1.4], [0.25, 0.25, 0.45]), [CHAIR], ["chair"], "robot1", 20)
        assert r1.created == 1 and r2.created == 0 and r2.associated == 1
        assert len(omap.nodes) == 1
        (msg,) = omap.messages()
        assert msg.label == "chair" and msg.observation_count == 2
        assert msg.sources == ["cam0", "robot1"]
        assert (msg.first_seen_ns, msg.last_seen_ns) == (10, 20)
        assert np.allclose(msg.box.center, [0.25, 0.25, 0.45], atol=0.06)

    @pytest.mark.parametrize("labels", [["chair", "chair"], ["chair", "table"]])
    def test_neighbouring_objects_stay_two(self, labels: list[str]) -> None:
        omap = ObjectMap(FusionConfig())
        for T in (look_at([0.5, -2.0, 1.6], [0.5, 0.25, 0.45]), look_at([0.6, -1.8, 1.2], [0.5, 0.25, 0.45])):
            observe(omap, T, [CHAIR, CHAIR2], labels)
        omap.maintain()
        assert len(omap.nodes) == 2
        centres = sorted(m.box.center[0] for m in omap.messages())
        assert centres == pytest.approx([0.25, 0.81], abs=0.06)

    @pytest.mark.parametrize("one_node_per_view", [True, False])
    def test_two_detections_of_one_view_never_join_one_node(self, one_node_per_view: bool) -> None:
        # A node smeared over two books on a shelf (an earlier view's wrong depth); a view then shows the two
        # books side by side: both overlap the node, but one view's two detections are two objects.
        rng = np.random.default_rng(1)

        def book(x0: float) -> np.ndarray:
            return book_points(rng, x0)

        omap = ObjectMap(FusionConfig(one_node_per_view=one_node_per_view))
        d = label_descriptor("book")
        omap.integrate([Object3D(np.concatenate([book(0.0), book(0.05), book(0.1)]), "book", 0.9, d)], "r", 1)
        res = omap.integrate([Object3D(book(0.0), "book", 0.9, d), Object3D(book(0.1), "book", 0.9, d)], "r", 2)
        if one_node_per_view:
            assert res.associated == 1 and res.created == 1 and len(omap.nodes) == 2
        else:  # the old behaviour: the node swallows both
            assert res.associated == 2 and len(omap.nodes) == 1

    @staticmethod
    def _slab(rng: np.random.Generator, x0: float, x1: float, y1: float) -> np.ndarray:
        return np.column_stack([rng.uniform(x0, x1, 600), rng.uniform(0.0, y1, 600),
                                rng.uniform(0.0, 0.9, 600)]).astype(np.float32)

    @pytest.mark.parametrize("growth_factor", [1.5, 0.0])
    def test_a_chain_of_overlapping_neighbours_is_not_one_node(self, growth_factor: float) -> None:
        # Dining chairs in a row, 0.35 m apart; each view's chair (its depth a little smeared) overlaps the node
        # of the chair before it. Without the growth limit the first node swallows the whole row.
        rng = np.random.default_rng(2)
        cfg = FusionConfig(growth_factor=growth_factor, merge_every_updates=1000)
        omap = ObjectMap(cfg)
        d = label_descriptor("dining chair")
        for k in range(4):
            omap.integrate([Object3D(self._slab(rng, 0.35 * k, 0.35 * k + 0.45, 0.45), "dining chair", 0.9, d)],
                           "r", k + 1)
        if growth_factor == 0.0:  # the old behaviour
            assert len(omap.nodes) == 1
            return
        assert len(omap.nodes) == 2
        one_view = float(np.hypot(0.45, 0.45))
        for node in omap.nodes.values():
            assert node.view_size_m == pytest.approx(one_view, abs=0.01)
            lo, hi = node.aabb
            assert np.hypot(*(hi - lo)[:2]) <= growth_factor * node.view_size_m + cfg.growth_slack_m
        # The refused chair started its own node where it is.
        assert sorted(round(float(n.points[:, 0].max()), 1) for n in omap.nodes.values()) == [1.1, 1.5]

    def test_an_object_seen_in_overlapping_parts_stays_one_node(self) -> None:
        # A 2.2 m sofa, each view showing 1.2 m of it: the node grows to the whole sofa, within the limit.
        rng = np.random.default_rng(3)
        omap = ObjectMap(FusionConfig(merge_every_updates=1000))
        d = label_descriptor("sofa")
        for k, x0 in enumerate((0.0, 0.6, 1.0)):
            omap.integrate([Object3D(self._slab(rng, x0, x0 + 1.2, 0.9), "sofa", 0.9, d)], "r", k + 1)
        (node,) = omap.nodes.values()
        assert node.observations == 3 and node.points[:, 0].max() == pytest.approx(2.2, abs=0.02)

    @pytest.mark.parametrize("keep_told_apart", [True, False])
    def test_two_books_one_keyframe_showed_apart_are_never_merged(self, keep_told_apart: bool) -> None:
        # Two books side by side, 5 cm apart: their points overlap at the overlap radius, so duplicate merging
        # takes them for one object, although one keyframe showed them as two detections.
        rng = np.random.default_rng(4)

        def book(x0: float) -> np.ndarray:
            return book_points(rng, x0)

        omap = ObjectMap(FusionConfig(keep_told_apart=keep_told_apart, merge_every_updates=1000))
        d = label_descriptor("book")
        res = omap.integrate([Object3D(book(0.0), "book", 0.9, d), Object3D(book(0.05), "book", 0.9, d)], "r", 1)
        assert res.created == 2
        res = omap.maintain()
        if keep_told_apart:
            assert res.merged_duplicates == 0 and len(omap.nodes) == 2
        else:  # the old behaviour
            assert res.merged_duplicates == 1 and len(omap.nodes) == 1
        # Two sightings in different keyframes are still merged as duplicates.
        other = ObjectMap(FusionConfig(keep_told_apart=keep_told_apart, merge_every_updates=1000,
                                       match_threshold=5.0))
        other.integrate([Object3D(book(0.0), "book", 0.9, d)], "r", 1)
        other.integrate([Object3D(book(0.01), "book", 0.9, d)], "r", 2)
        assert len(other.nodes) == 2 and other.maintain().merged_duplicates == 1

    def test_no_valid_depth_is_dropped_and_counted(self) -> None:
        cfg = FusionConfig()
        T = look_at([2.0, -1.5, 1.5], [0.25, 0.25, 0.45])
        depth, idx = raycast(T, [CHAIR])
        mask = np.zeros_like(idx, dtype=bool)
        mask[:10, :10] = True  # sky: no depth there
        dets = detections(idx, ["chair"]) + [
            Detection(mask=mask, label="ghost", confidence=1.0, descriptor=label_descriptor("ghost"))
        ]
        conf = np.ones_like(depth)
        objs, stats = lift_detections(dets, world_points(T, depth), conf, depth, cfg)
        assert [o.label for o in objs] == ["chair"]
        assert stats.dropped_no_depth == 1 and stats.lifted == 1
        # Low-confidence depth counts as no depth.
        objs, stats = lift_detections(dets[:1], world_points(T, depth), conf * 0.1, depth, cfg)
        assert objs == [] and stats.dropped_no_depth == 1

    def test_prune_and_duplicate_merge(self) -> None:
        cfg = FusionConfig(merge_every_updates=1, min_observations=2, prune_after_updates=2, match_threshold=5.0)
        omap = ObjectMap(cfg)
        T = look_at([2.0, -1.5, 1.5], [0.25, 0.25, 0.45])
        # match_threshold unreachable: every view creates a node; maintenance must fold the duplicate.
        observe(omap, T, [CHAIR], ["chair"])
        r, _ = observe(omap, T, [CHAIR], ["chair"])
        assert r.merged_duplicates == 1 and len(omap.nodes) == 1 and r.removed == {"n000002"}
        assert omap.messages()[0].observation_count == 2
        # A lone sighting of something else is dropped once it is old enough.
        observe(omap, look_at([3, 3, 1.5], [4, 4, 0.4]), [(np.array([4.0, 4, 0]), np.array([4.3, 4.3, 0.4]))], ["box"])
        assert "n000003" in omap.nodes
        r, _ = observe(omap, T, [], [])
        r, _ = observe(omap, T, [], [])
        assert "n000003" not in omap.nodes and "n000003" in r.removed

    def test_points_capped_and_state_round_trip(self) -> None:
        cfg = FusionConfig(max_points_per_node=50, voxel_m=0.01)
        omap = ObjectMap(cfg)
        observe(omap, look_at([2.0, -1.5, 1.5], [0.25, 0.25, 0.45]), [CHAIR], ["chair"])
        assert max(len(n.points) for n in omap.nodes.values()) == 50
        other = ObjectMap(cfg)
        other.load_state(omap.state())
        assert other.messages() == omap.messages() and other.next_id == omap.next_id
        assert [n.view_size_m for n in other.nodes.values()] == [n.view_size_m for n in omap.nodes.values()]
        assert all(n.view_size_m > 0 for n in other.nodes.values())
        # A state written before the growth limit: each node's own size stands for its largest observation.
        old = omap.state()
        for d in old["nodes"]:
            del d["view_size_m"]
        other.load_state(old)
        for node in other.nodes.values():
            lo, hi = node.points.min(0), node.points.max(0)
            assert node.view_size_m == pytest.approx(float(np.hypot(*(hi - lo)[:2])))


def test_rows_all_is_np_all_over_the_last_axis() -> None:
    from mapper.fusion import rows_all

    rng = np.random.default_rng(7)
    for shape in ((0, 3), (5, 3), (4, 6, 3), (7, 1), (3, 0)):
        m = rng.uniform(size=shape) < 0.8
        assert np.array_equal(rows_all(m), np.all(m, axis=-1))
