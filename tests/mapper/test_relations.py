"""Relation predicates over hand-built oriented boxes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapper.relations import (
    RelationConfig,
    compute_edges,
    footprint,
    footprint_gap,
    footprint_intersection_area,
    refine_with_points,
    relation,
)
from protocol.messages import OrientedBox


def box(cx: float, cy: float, zmin: float, ex: float, ey: float, ez: float, yaw: float = 0.0) -> OrientedBox:
    return OrientedBox(center=(cx, cy, zmin + ez / 2), extent=(ex, ey, ez), yaw_rad=yaw)


TABLE = box(0.0, 0.0, 0.0, 1.2, 0.8, 0.75)


class TestFootprint:
    def test_intersection_of_rotated_squares(self) -> None:
        a = footprint(box(0, 0, 0, 2, 2, 1))
        b = footprint(box(0, 0, 0, 2, 2, 1, yaw=math.pi / 4))
        # A square and the same square turned 45 degrees share a regular octagon: 8 (sqrt2 - 1) for side 2.
        assert footprint_intersection_area(a, b) == pytest.approx(8 * (math.sqrt(2) - 1), rel=1e-9)

    def test_disjoint_and_gap(self) -> None:
        a = footprint(box(0, 0, 0, 1, 1, 1))
        b = footprint(box(3, 0, 0, 1, 1, 1))
        assert footprint_intersection_area(a, b) == 0.0
        assert footprint_gap(a, b) == pytest.approx(2.0)
        assert footprint_gap(a, footprint(box(0.5, 0, 0, 1, 1, 1))) == 0.0


class TestPredicates:
    def test_on_top_of(self) -> None:
        cup = box(0.1, 0.1, 0.75, 0.08, 0.08, 0.1)
        assert relation(cup, TABLE) == "on_top_of"
        # The reverse pair is not "on top of"; the table is below the cup in contact, so nothing else fires
        # except it is not inside or next to the cup either.
        assert relation(TABLE, cup) is None

    def test_on_top_of_needs_footprint_overlap(self) -> None:
        hanging = box(0.65, 0.0, 0.75, 0.3, 0.3, 0.1)  # mostly beyond the table's edge (x from 0.5 to 0.8)
        assert relation(hanging, TABLE) != "on_top_of"

    def test_over_and_under(self) -> None:
        lamp = box(0.0, 0.0, 1.5, 0.3, 0.3, 0.2)  # 0.75 m above the table top
        assert relation(lamp, TABLE) == "over"
        assert relation(TABLE, lamp) == "under"
        too_high = box(0.0, 0.0, 2.5, 0.3, 0.3, 0.2)
        assert relation(too_high, TABLE) is None

    def test_inside(self) -> None:
        cabinet = box(0.0, 0.0, 0.0, 1.0, 0.5, 2.0)
        book = box(0.1, 0.0, 0.9, 0.3, 0.2, 0.25)
        assert relation(book, cabinet) == "inside"
        assert relation(cabinet, book) is None

    def test_next_to(self) -> None:
        chair = box(0.9, 0.0, 0.0, 0.45, 0.45, 0.9)  # 0.075 m from the table's edge
        assert relation(chair, TABLE) == "next_to"
        assert relation(TABLE, chair) == "next_to"
        far_chair = box(2.0, 0.0, 0.0, 0.45, 0.45, 0.9)
        assert relation(far_chair, TABLE) is None

    def test_next_to_needs_similar_height(self) -> None:
        shelf = box(0.9, 0.0, 1.6, 0.4, 0.3, 0.3)  # beside the table but well above it
        assert relation(shelf, TABLE) is None

    def test_rotation_matters(self) -> None:
        # A long thin bench centred 1.0 m from the table's axis: lying along x its near side is 0.45 m
        # from the table (too far); turned along y it reaches to 0.1 m from the table.
        bench = box(0.0, 1.0, 0.0, 1.2, 0.3, 0.45)
        assert relation(bench, TABLE) is None
        turned = box(0.0, 1.1, 0.0, 1.2, 0.3, 0.45, yaw=math.pi / 2)
        assert relation(turned, TABLE) == "next_to"


class TestPriority:
    def test_on_top_of_beats_inside(self) -> None:
        # A thin mat lying on the table, sunk slightly into its box: within the table's volume AND in
        # contact with its top; on_top_of has priority over inside.
        mat = box(0.0, 0.0, 0.70, 0.4, 0.3, 0.06)
        cfg = RelationConfig()
        assert relation(mat, TABLE, cfg) == "on_top_of"
        no_contact = cfg.model_copy(update={"max_penetration_m": 0.0})
        assert relation(mat, TABLE, no_contact) == "inside"

    def test_over_beats_next_to(self) -> None:
        # A small box above the table within next_to reach in z-overlap terms is still "over" first.
        picture = box(0.3, 0.0, 0.9, 0.3, 0.05, 0.3)
        cfg = RelationConfig(next_to_max_base_dz_m=5.0, next_to_min_vertical_overlap=0.0)
        assert relation(picture, TABLE, cfg) == "over"

    def test_one_edge_per_ordered_pair(self) -> None:
        boxes = {
            "table": TABLE,
            "cup": box(0.1, 0.1, 0.75, 0.08, 0.08, 0.1),
            "chair": box(0.9, 0.0, 0.0, 0.45, 0.45, 0.9),
            "lamp": box(0.0, 0.0, 1.5, 0.3, 0.3, 0.2),
            "far": box(10.0, 10.0, 0.0, 1.0, 1.0, 1.0),
        }
        edges = compute_edges(boxes)
        pairs = [(e.subject_id, e.object_id) for e in edges]
        assert len(pairs) == len(set(pairs))
        triples = {(e.subject_id, e.predicate, e.object_id) for e in edges}
        assert ("cup", "on_top_of", "table") in triples
        assert ("chair", "next_to", "table") in triples
        assert ("lamp", "over", "table") in triples
        assert ("table", "under", "lamp") in triples
        assert not any("far" in p for p in pairs)
        # Deterministic: same input, same output, in sorted order.
        assert compute_edges(dict(reversed(list(boxes.items())))) == edges
        assert [(e.subject_id, e.predicate, e.object_id) for e in edges] == sorted(triples)

    def test_empty_and_single(self) -> None:
        assert compute_edges({}) == []
        assert compute_edges({"a": TABLE}) == []

    def test_matches_pairwise(self) -> None:
        rng = np.random.default_rng(0)
        boxes = {
            f"n{i}": box(*rng.uniform(-2, 2, 2), rng.uniform(0, 1), *rng.uniform(0.1, 1.0, 3), rng.uniform(-3, 3))
            for i in range(25)
        }
        got = {(e.subject_id, e.object_id): e.predicate for e in compute_edges(boxes)}
        for a in boxes:
            for b in boxes:
                if a != b:
                    assert got.get((a, b)) == relation(boxes[a], boxes[b])


class TestRefineWithPoints:
    def _grid(self, x0, x1, y0, y1, z0, z1, step=0.05):
        g = np.mgrid[x0:x1:step, y0:y1:step, z0:z1:step].reshape(3, -1).T
        return g

    def test_pillow_on_bed_with_headboard_is_on_top_of(self) -> None:
        bed = box(0.0, 0.0, 0.0, 2.0, 1.6, 1.0)
        pillow = box(-0.6, 0.0, 0.5, 0.4, 0.5, 0.15)
        assert relation(pillow, bed) == "inside"
        mattress = self._grid(-1.0, 1.0, -0.8, 0.8, 0.45, 0.5)
        headboard = self._grid(-1.0, -0.95, -0.8, 0.8, 0.0, 1.0)
        bed_pts = np.concatenate([mattress, headboard])
        edges = compute_edges({"pillow": pillow, "bed": bed})
        got = refine_with_points(edges, {"pillow": pillow, "bed": bed}, {"bed": bed_pts})
        assert ("pillow", "on_top_of", "bed") in {(e.subject_id, e.predicate, e.object_id) for e in got}

    def test_book_in_shelf_and_bottle_in_tub_stay_inside(self) -> None:
        shelf = box(0.0, 0.0, 0.0, 1.0, 0.4, 1.8)
        book = box(0.0, 0.0, 0.62, 0.2, 0.25, 0.25)
        boards = np.concatenate([self._grid(-0.5, 0.5, -0.2, 0.2, z, z + 0.02) for z in (0.6, 1.2, 1.78)])
        e = compute_edges({"book": book, "shelf": shelf})
        got = refine_with_points(e, {"book": book, "shelf": shelf}, {"shelf": boards})
        assert ("book", "inside", "shelf") in {(x.subject_id, x.predicate, x.object_id) for x in got}
        tub = box(0.0, 0.0, 0.0, 1.7, 0.8, 0.6)
        bottle = box(0.2, 0.0, 0.05, 0.08, 0.08, 0.25)
        walls = np.concatenate([
            self._grid(-0.85, 0.85, -0.4, -0.35, 0.0, 0.6), self._grid(-0.85, 0.85, 0.35, 0.4, 0.0, 0.6),
            self._grid(-0.85, -0.8, -0.4, 0.4, 0.0, 0.6), self._grid(0.8, 0.85, -0.4, 0.4, 0.0, 0.6),
        ])
        e = compute_edges({"bottle": bottle, "tub": tub})
        got = refine_with_points(e, {"bottle": bottle, "tub": tub}, {"tub": walls})
        assert ("bottle", "inside", "tub") in {(x.subject_id, x.predicate, x.object_id) for x in got}


    def test_cache_gives_the_uncached_edges(self, monkeypatch: pytest.MonkeyPatch) -> None:
        """Keyframe after keyframe some boxes move and some clouds are replaced: the cached refinement (one
        cache for compute_edges and refine_with_points, as the mapper keeps) equals the uncached one."""
        from mapper import relations

        calls = {"uncached": 0, "cached": 0}
        mode = "uncached"
        real = relations._encloses

        def counted(*args: object) -> bool:
            calls[mode] += 1
            return real(*args)

        monkeypatch.setattr(relations, "_encloses", counted)
        rng = np.random.default_rng(2)

        def some_box() -> OrientedBox:  # big ones and small ones, many inside one another
            return box(*rng.uniform(-0.5, 0.5, 2), rng.uniform(0, 0.5), *np.exp(rng.uniform(-2.5, 0.7, 3)), 0.0)

        boxes = {f"n{i}": some_box() for i in range(20)}
        clouds = {k: rng.uniform(-1, 1, (200, 3)) * 0.5 * np.asarray(b.extent) + np.asarray(b.center)
                  for k, b in boxes.items()}
        cache = relations.EdgeCache()
        for step in range(12):
            for k in rng.choice(sorted(boxes), 4, replace=False):
                if rng.uniform() < 0.5:
                    boxes[k] = some_box()
                else:
                    clouds[k] = clouds[k] + rng.normal(0, 0.05, (1, 3))
            cfg = RelationConfig(enclosure_min_sides=2) if step == 8 else RelationConfig()
            mode = "uncached"
            want = refine_with_points(compute_edges(boxes, cfg), boxes, clouds, cfg)
            mode = "cached"
            got = refine_with_points(compute_edges(boxes, cfg, cache), boxes, clouds, cfg, cache)
            assert got == want, step
        assert 0 < calls["cached"] < calls["uncached"] / 2, calls

def test_compiled_clip_equals_python_clip() -> None:
    from mapper import relations

    if relations._clip_compiled is None:
        pytest.skip("numba not installed")
    rng = np.random.default_rng(3)

    def square(cx: float, cy: float, sx: float, sy: float, yaw: float) -> np.ndarray:
        c, s = math.cos(yaw), math.sin(yaw)
        local = np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]]) / 2.0
        return local @ np.array([[c, s], [-s, c]]) + [cx, cy]

    for k in range(300):
        a = square(*rng.normal(size=2), *rng.uniform(0.1, 1.0, 2), rng.uniform(0, 3))
        b = a.copy() if k % 10 == 0 else square(*rng.normal(size=2), *rng.uniform(0.1, 1.0, 2), rng.uniform(0, 3))
        got, want = relations._clip(a, b), relations._clip_python(a, b)
        assert got.shape == want.shape and np.array_equal(got, want)


def test_gap_estimate_decides_as_footprint_gap() -> None:
    from mapper import relations

    rng = np.random.default_rng(4)
    for k in range(300):
        a = footprint(OrientedBox(center=(*rng.normal(size=2), 0.0), extent=(*rng.uniform(0.05, 1.0, 2), 1.0),
                                  yaw_rad=float(rng.uniform(-0.8, 0.8))))
        b = footprint(OrientedBox(center=(*rng.normal(size=2), 0.0), extent=(*rng.uniform(0.05, 1.0, 2), 1.0),
                                  yaw_rad=float(rng.uniform(-0.8, 0.8))))
        inter = footprint_intersection_area(a, b)
        gap = footprint_gap(a, b)
        if inter == 0.0:
            assert relations._gap_estimate(a, b) == pytest.approx(gap, abs=1e-12)
        # thresholds far from the gap, and at it (there only footprint_gap itself can decide)
        for gap_max in (gap - 0.05, gap, gap + 0.05, np.nextafter(gap, 0.0), np.nextafter(gap, 1.0)):
            assert relations._gap_at_most(a, b, inter, gap_max) == (gap <= gap_max), k


def test_compiled_gap_estimate_equals_the_numpy_estimate(monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled point-segment search gives the numpy estimate's gap to rounding, far inside _gap_at_most's
    margin (so both decide every comparison alike)."""
    from mapper import relations

    if relations._gap_compiled is None:
        pytest.skip("numba not installed")
    rng = np.random.default_rng(7)
    for _ in range(200):
        boxes = [OrientedBox(center=(*rng.normal(size=2) * 3, 0.5), extent=tuple(rng.uniform(0.1, 2.0, 3)),
                             yaw_rad=float(rng.uniform(-3, 3))) for _ in range(2)]
        a, b = (relations.footprint(box, 1e-3) for box in boxes)
        compiled = relations._gap_estimate(a, b)
        with monkeypatch.context() as m:
            m.setattr(relations, "_gap_compiled", None)
            reference = relations._gap_estimate(a, b)
        assert abs(compiled - reference) <= 1e-12 * (1.0 + max(np.abs(a).max(), np.abs(b).max()))
