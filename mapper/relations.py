"""Relation edges from gravity-aligned oriented boxes: deterministic, geometry only (no I/O).

For every ordered pair ``(a, b)`` the predicates are tried in a fixed priority order and the first
that holds becomes the single edge ``a <predicate> b``:

1. ``on_top_of``: a rests on b: a's bottom is within ``contact_gap_m`` of b's top and most of a's
   footprint lies over b's footprint.
2. ``over`` / ``under``: vertical adjacency without contact: a is above (``over``) or below
   (``under``) b with a vertical gap up to ``max_vertical_gap_m`` and overlapping footprints.
3. ``inside``: most of a's volume lies within b's box (and a is the smaller).
4. ``next_to``: the footprints are at most ``next_to_max_gap_m`` apart horizontally and the two
   stand at a similar height (bottoms close and vertical extents overlapping).

Boxes are :class:`protocol.messages.OrientedBox`: a centre, full extents along the box axes and a yaw
about world z (metres, z up).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.geometry.kernels import compiled
from protocol.messages import GraphEdge, OrientedBox, Predicate


class RelationConfig(BaseModel):
    """Thresholds of the relation predicates (fixed per dataset, as in the paper)."""

    model_config = ConfigDict(extra="forbid")
    contact_gap_m: float = Field(
        default=0.06, ge=0.0, description="on_top_of: max |bottom of a - top of b| for vertical contact"
    )
    max_penetration_m: float = Field(
        default=0.08, ge=0.0, description="on_top_of: how far a's bottom may sink below b's top (box slack)"
    )
    min_footprint_overlap: float = Field(
        default=0.5, ge=0.0, le=1.0, description="on_top_of: footprint intersection / footprint area of a"
    )
    max_vertical_gap_m: float = Field(
        default=1.0, gt=0.0, description="over/under: largest vertical gap still counted as adjacent"
    )
    min_vertical_footprint_overlap: float = Field(
        default=0.3, ge=0.0, le=1.0, description="over/under: footprint intersection / smaller footprint"
    )
    min_inside_fraction: float = Field(
        default=0.8, ge=0.0, le=1.0, description="inside: fraction of a's volume within b's box"
    )
    next_to_max_gap_m: float = Field(
        default=0.3, ge=0.0, description="next_to: largest horizontal gap between the footprints"
    )
    next_to_max_gap_items_m: float = Field(
        default=0.12, ge=0.0, description="next_to: largest gap when both stand off the floor (items on furniture)"
    )
    item_min_base_z_m: float = Field(
        default=0.15, description="objects whose bottom is higher than this stand on furniture (items)"
    )
    next_to_max_base_dz_m: float = Field(
        default=0.25, ge=0.0, description="next_to: largest difference between the two bottoms"
    )
    next_to_min_vertical_overlap: float = Field(
        default=0.3, ge=0.0, le=1.0, description="next_to: vertical overlap / the smaller height"
    )
    next_to_max_footprint_overlap: float = Field(
        default=0.5, ge=0.0, le=1.0,
        description="next_to: footprints overlapping more than this (of the smaller) are not 'next to'",
    )
    min_extent_m: float = Field(default=0.01, gt=0.0, description="extents are clamped to at least this")
    enclosure_min_sides: int = Field(
        default=3, ge=0, le=4,
        description="inside (with point clouds): b must cover a from above or wall it in on this many sides; "
        "otherwise a rests on an inner surface of b (pillow on a bed with a tall headboard): on_top_of",
    )


@dataclass(frozen=True)
class _Box:
    corners_xy: np.ndarray  # (4, 2) counter-clockwise footprint
    zmin: float
    zmax: float
    area: float
    volume: float
    center: np.ndarray  # (3,)
    extent: np.ndarray  # (3,)
    yaw: float
    diagonal: float  # np.hypot of the footprint's sides (asked for once per pair: kept)


def footprint(box: OrientedBox, min_extent_m: float = 0.0) -> np.ndarray:
    """(4, 2) footprint corners of ``box`` in world xy, counter-clockwise."""
    ex = max(box.extent[0], min_extent_m) / 2.0
    ey = max(box.extent[1], min_extent_m) / 2.0
    c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    local = np.array([[-ex, -ey], [ex, -ey], [ex, ey], [-ex, ey]])
    R = np.array([[c, -s], [s, c]])
    return local @ R.T + np.asarray(box.center[:2])


def _prep(box: OrientedBox, min_extent_m: float) -> _Box:
    ext = np.maximum(np.asarray(box.extent, dtype=np.float64), min_extent_m)
    cz = box.center[2]
    return _Box(
        corners_xy=footprint(box, min_extent_m),
        zmin=cz - ext[2] / 2.0,
        zmax=cz + ext[2] / 2.0,
        area=float(ext[0] * ext[1]),
        volume=float(ext.prod()),
        center=np.asarray(box.center, dtype=np.float64),
        extent=ext,
        yaw=box.yaw_rad,
        diagonal=np.hypot(*ext[:2]),
    )


def _clip(subject: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: ``subject`` polygon clipped by the convex counter-clockwise ``clipper``."""
    if _clip_compiled is not None:
        # Compiled: the same arithmetic in the same order (identical vertices), without a Python loop per vertex
        # (edges of a few hundred box pairs per keyframe).
        buf = np.empty((2, len(subject) + len(clipper) + 1, 2))
        n = _clip_compiled(np.ascontiguousarray(subject, np.float64), np.ascontiguousarray(clipper, np.float64), buf)
        return buf[0, :n].copy() if n else np.zeros((0, 2))
    return _clip_python(subject, clipper)


def _clip_python(subject: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    out = subject
    n = len(clipper)
    for i in range(n):
        if len(out) == 0:
            break
        a, b = clipper[i], clipper[(i + 1) % n]
        edge = b - a
        inp = out
        side = edge[0] * (inp[:, 1] - a[1]) - edge[1] * (inp[:, 0] - a[0])
        pts: list[np.ndarray] = []
        m = len(inp)
        for j in range(m):
            p, q = inp[j], inp[(j + 1) % m]
            sp, sq = side[j], side[(j + 1) % m]
            if sp >= 0:
                pts.append(p)
            if (sp >= 0) != (sq >= 0):
                t = sp / (sp - sq)
                pts.append(p + t * (q - p))
        out = np.array(pts) if pts else np.zeros((0, 2))
    return out


def _clip_loops(subject: Any, clipper: Any, buf: Any) -> int:  # pragma: no cover - compiled
    # buf (2, N, 2): two vertex lists taking turns (input, output); returns the vertices left in buf[0].
    m = subject.shape[0]
    for j in range(m):
        buf[0, j, 0] = subject[j, 0]
        buf[0, j, 1] = subject[j, 1]
    n = clipper.shape[0]
    cur = 0
    for i in range(n):
        if m == 0:
            break
        ax, ay = clipper[i, 0], clipper[i, 1]
        ex, ey = clipper[(i + 1) % n, 0] - ax, clipper[(i + 1) % n, 1] - ay
        src, dst = buf[cur], buf[1 - cur]
        k = 0
        for j in range(m):
            j1 = (j + 1) % m
            px, py, qx, qy = src[j, 0], src[j, 1], src[j1, 0], src[j1, 1]
            sp = ex * (py - ay) - ey * (px - ax)
            sq = ex * (qy - ay) - ey * (qx - ax)
            if sp >= 0:
                dst[k, 0] = px
                dst[k, 1] = py
                k += 1
            if (sp >= 0) != (sq >= 0):
                t = sp / (sp - sq)
                dst[k, 0] = px + t * (qx - px)
                dst[k, 1] = py + t * (qy - py)
                k += 1
        m = k
        cur = 1 - cur
    if cur == 1:
        for j in range(m):
            buf[0, j, 0] = buf[1, j, 0]
            buf[0, j, 1] = buf[1, j, 1]
    return m


_clip_compiled = compiled(_clip_loops)  # None without numba (optional, the ``server`` extra)


def _poly_area(poly: np.ndarray) -> float:
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    # the rolled coordinates (np.roll(v, -1)) by slicing: the same values, without np.roll's per-call overhead
    return float(0.5 * abs(np.dot(x, np.concatenate((y[1:], y[:1]))) - np.dot(y, np.concatenate((x[1:], x[:1])))))


def footprint_intersection_area(a: np.ndarray, b: np.ndarray) -> float:
    """Area of the intersection of two convex counter-clockwise polygons (m^2)."""
    return _poly_area(_clip(a, b))


def _seg_point_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances from points ``p`` (K, 2) to the segment ab."""
    ab = b - a
    denom = float(ab @ ab)
    t = np.zeros(len(p)) if denom == 0.0 else np.clip(((p - a) @ ab) / denom, 0.0, 1.0)
    proj = a + t[:, None] * ab
    return np.linalg.norm(p - proj, axis=1)


def footprint_gap(a: np.ndarray, b: np.ndarray, inter: float | None = None) -> float:
    """Horizontal distance between two convex polygons (0 when they touch or overlap). ``inter``: their
    :func:`footprint_intersection_area` when the caller has it."""
    if (footprint_intersection_area(a, b) if inter is None else inter) > 0.0:
        return 0.0
    best = math.inf
    for P, Q in ((a, b), (b, a)):
        for i in range(len(Q)):
            best = min(best, float(_seg_point_dist(P, Q[i], Q[(i + 1) % len(Q)]).min()))
    return best


def _gap_loops(a: Any, b: Any) -> float:  # pragma: no cover - compiled
    # _gap_estimate's point-segment distances one at a time: the smallest squared one, its square root.
    best = np.inf
    for side in range(2):
        P, Q = (a, b) if side == 0 else (b, a)
        n = Q.shape[0]
        for s in range(n):
            ax, ay = Q[s, 0], Q[s, 1]
            abx, aby = Q[(s + 1) % n, 0] - ax, Q[(s + 1) % n, 1] - ay
            denom = abx * abx + aby * aby
            for k in range(P.shape[0]):
                apx, apy = P[k, 0] - ax, P[k, 1] - ay
                t = 0.0
                if denom > 0.0:
                    t = min(max((apx * abx + apy * aby) / denom, 0.0), 1.0)
                dx, dy = apx - t * abx, apy - t * aby
                best = min(best, dx * dx + dy * dy)
    return math.sqrt(best)


_gap_compiled = compiled(_gap_loops)  # None without numba (optional, the ``server`` extra)


def _gap_estimate(a: np.ndarray, b: np.ndarray) -> float:
    """:func:`footprint_gap` of two disjoint convex polygons in one vectorised pass (all point-segment distances
    at once): the same distance up to rounding (not bit for bit), for deciding comparisons that are not close.
    Compiled where numba is installed (a loop per distance, ~100x less overhead than the numpy calls)."""
    if _gap_compiled is not None:
        return float(_gap_compiled(np.ascontiguousarray(a, np.float64), np.ascontiguousarray(b, np.float64)))
    dists = []
    for P, Q in ((a, b), (b, a)):
        A = Q
        ab = np.concatenate((Q[1:], Q[:1])) - A  # (S, 2) segment vectors
        ap = P[:, None, :] - A[None, :, :]  # (K, S, 2)
        denom = np.sum(ab * ab, axis=1)
        t = np.clip(np.sum(ap * ab, axis=2) / np.where(denom > 0.0, denom, 1.0), 0.0, 1.0) * (denom > 0.0)
        d = ap - t[:, :, None] * ab
        dists.append(np.sqrt(np.min(np.sum(d * d, axis=2))))
    return float(min(dists))


def _gap_at_most(a: np.ndarray, b: np.ndarray, inter: float, gap_max: float) -> bool:
    """``footprint_gap(a, b, inter) <= gap_max``: by :func:`_gap_estimate` when it is clear of ``gap_max`` by far
    more than rounding can move either (a millionth of a millimetre per metre of coordinates), by
    :func:`footprint_gap` itself otherwise: the same answer, without eight small numpy calls per pair."""
    if inter > 0.0:
        return 0.0 <= gap_max
    est = _gap_estimate(a, b)
    margin = 1e-9 * (1.0 + float(max(np.abs(a).max(), np.abs(b).max())))
    if abs(est - gap_max) > margin:
        return est < gap_max
    return footprint_gap(a, b, inter) <= gap_max


def _inside_fraction(a: _Box, b: _Box, inter: float | None = None) -> float:
    """Fraction of a's volume within b (footprints exact, heights as intervals). ``inter``: the footprints'
    intersection area when the caller has it."""
    dz = max(0.0, min(a.zmax, b.zmax) - max(a.zmin, b.zmin))
    if inter is None:
        inter = footprint_intersection_area(a.corners_xy, b.corners_xy)
    return inter * dz / a.volume if a.volume > 0 else 0.0


def relation(a_box: OrientedBox, b_box: OrientedBox, cfg: RelationConfig | None = None) -> str | None:
    """The one predicate of ``a -> b`` (highest priority that holds), or None."""
    cfg = cfg or RelationConfig()
    return _relation(_prep(a_box, cfg.min_extent_m), _prep(b_box, cfg.min_extent_m), cfg)


def _relation(a: _Box, b: _Box, cfg: RelationConfig) -> Predicate | None:
    # Cheap reject: footprints far apart horizontally cannot relate at all.
    reach = cfg.next_to_max_gap_m + 0.5 * (a.diagonal + b.diagonal)
    apart = np.hypot(*(a.center[:2] - b.center[:2]))
    if apart > reach:
        return None
    # The footprints' intersection (the costly part) is worked out once, and only when a predicate's height
    # test holds: each test below asks for it after its height conditions, so the first that holds decides as
    # if it had been computed up front.
    inter: float | None = None

    def overlap() -> float:
        nonlocal inter
        if inter is None:
            inter = footprint_intersection_area(a.corners_xy, b.corners_xy)
        return inter

    min_area = min(a.area, b.area)
    # 1. on_top_of: a's bottom touches b's top, a mostly over b, a's centre above b's.
    bottom_to_top = a.zmin - b.zmax
    if (
        -cfg.max_penetration_m <= bottom_to_top <= cfg.contact_gap_m
        and a.center[2] > b.center[2]
        and overlap() >= cfg.min_footprint_overlap * a.area
    ):
        return "on_top_of"
    # 2. over / under: stacked with a clear gap.
    over = cfg.contact_gap_m < a.zmin - b.zmax <= cfg.max_vertical_gap_m
    under = cfg.contact_gap_m < b.zmin - a.zmax <= cfg.max_vertical_gap_m
    if (over or under) and overlap() >= cfg.min_vertical_footprint_overlap * min_area:
        return "over" if over else "under"
    # 3. inside: a's volume mostly within the larger b (no height overlap: nothing inside, whatever the footprints).
    if a.volume < b.volume and _inside_fraction(
        a, b, overlap() if min(a.zmax, b.zmax) > max(a.zmin, b.zmin) else 0.0
    ) >= cfg.min_inside_fraction:
        return "inside"
    # 4. next_to: close footprints at a similar height. Items on furniture use a tighter gap, and the
    # centres must be close relative to the sizes (a long bed is not "next to" what lies beyond its foot).
    if abs(a.zmin - b.zmin) <= cfg.next_to_max_base_dz_m and overlap() <= cfg.next_to_max_footprint_overlap * min_area:
        items = min(a.zmin, b.zmin) > cfg.item_min_base_z_m
        gap_max = cfg.next_to_max_gap_items_m if items else cfg.next_to_max_gap_m
        dz = min(a.zmax, b.zmax) - max(a.zmin, b.zmin)
        min_h = min(a.zmax - a.zmin, b.zmax - b.zmin)
        reach = (max(a.extent[0], a.extent[1]) + max(b.extent[0], b.extent[1])) / 2.0 + gap_max
        if (
            dz >= cfg.next_to_min_vertical_overlap * min_h
            and apart <= reach
            and _gap_at_most(a.corners_xy, b.corners_xy, overlap(), gap_max)
        ):
            return "next_to"
    return None


class EdgeCache:
    """What :func:`compute_edges` found last time, per node and per ordered pair, keyed by the boxes' values: a
    keyframe changes a few nodes, so the pairs of unchanged boxes are not worked out again (the answer is the
    same: a predicate depends only on the two boxes and the config). Holds only the last call's nodes and
    near pairs (bounded by the graph)."""

    def __init__(self) -> None:
        self.prepared: dict[str, tuple[tuple[Any, ...], _Box]] = {}
        self.pairs: dict[tuple[str, str], tuple[tuple[Any, ...], tuple[Any, ...], Predicate | None]] = {}
        self.cfg: RelationConfig | None = None
        self.hits = 0
        # refine_with_points: per ``inside`` edge, the subject's box, the object's points array (the same object:
        # node clouds are replaced, never changed in place) and whether they enclose it; its own config.
        self.encloses: dict[tuple[str, str], tuple[tuple[Any, ...], np.ndarray, bool]] = {}
        self.encloses_cfg: RelationConfig | None = None


def _box_key(box: OrientedBox) -> tuple[Any, ...]:
    return (*box.center, *box.extent, box.yaw_rad)


def compute_edges(boxes: Mapping[str, OrientedBox], cfg: RelationConfig | None = None,
                  cache: EdgeCache | None = None) -> list[GraphEdge]:
    """All edges among ``boxes`` (node id -> box), at most one per ordered pair, sorted by triple. With a
    ``cache`` (one per graph), pairs whose boxes did not change since the last call are not recomputed."""
    cfg = cfg or RelationConfig()
    if cache is not None and cache.cfg != cfg:
        cache.prepared, cache.pairs, cache.cfg = {}, {}, cfg.model_copy()
    ids = sorted(boxes)
    keys = [_box_key(boxes[i]) for i in ids]
    if cache is None:
        prepared = [_prep(boxes[i], cfg.min_extent_m) for i in ids]
    else:
        prepared = []
        for i, k in zip(ids, keys, strict=True):
            hit = cache.prepared.get(i)
            prepared.append(hit[1] if hit is not None and hit[0] == k else _prep(boxes[i], cfg.min_extent_m))
        cache.prepared = {i: (k, b) for i, k, b in zip(ids, keys, prepared, strict=True)}
    if len(ids) < 2:
        return []
    # Vectorised horizontal pre-filter on circumscribed circles keeps this ~O(n) for sparse scenes.
    centers = np.array([p.center[:2] for p in prepared])
    radii = np.array([0.5 * p.diagonal for p in prepared])
    dist = np.linalg.norm(centers[:, None, :] - centers[None, :, :], axis=2)
    near = dist <= radii[:, None] + radii[None, :] + cfg.next_to_max_gap_m
    np.fill_diagonal(near, False)
    edges: list[GraphEdge] = []
    pairs: dict[tuple[str, str], tuple[tuple[Any, ...], tuple[Any, ...], Predicate | None]] = {}
    for i, j in zip(*(ix.tolist() for ix in np.nonzero(near)), strict=True):  # ints: fast list indexing
        if cache is None:
            pred = _relation(prepared[i], prepared[j], cfg)
        else:
            was = cache.pairs.get((ids[i], ids[j]))
            if was is not None and was[0] == keys[i] and was[1] == keys[j]:
                pred = was[2]
                cache.hits += 1
            else:
                pred = _relation(prepared[i], prepared[j], cfg)
            pairs[(ids[i], ids[j])] = (keys[i], keys[j], pred)
        if pred is not None:
            edges.append(GraphEdge(subject_id=ids[i], predicate=pred, object_id=ids[j]))
    if cache is not None:
        cache.pairs = pairs
    edges.sort(key=lambda e: (e.subject_id, e.predicate, e.object_id))
    return edges


def refine_with_points(
    edges: list[GraphEdge],
    boxes: Mapping[str, OrientedBox],
    clouds: Mapping[str, np.ndarray],
    cfg: RelationConfig | None = None,
    cache: EdgeCache | None = None,
) -> list[GraphEdge]:
    """Tell ``inside`` from resting on an inner surface using the nodes' points (world, metres).

    A box test alone cannot: a pillow on a bed whose headboard makes the box tall is "inside" the bed's
    box. ``a inside b`` is kept when b has points above a (a shelf board, a lid) or walls beside a (anywhere
    within b) at a's height on at least ``enclosure_min_sides`` of its four sides (a bathtub, a basket); otherwise
    the edge becomes ``a on_top_of b``. Other edges pass through unchanged. With a ``cache`` (one per graph), an
    edge whose subject box and object cloud are those of the last call is not worked out again.
    """
    cfg = cfg or RelationConfig()
    if cache is not None and cache.encloses_cfg != cfg:
        cache.encloses, cache.encloses_cfg = {}, cfg.model_copy()
    known: dict[tuple[str, str], tuple[tuple[Any, ...], np.ndarray, bool]] = {}
    out = []
    for e in edges:
        if e.predicate == "inside" and e.object_id in clouds:
            a_box, b_points = boxes[e.subject_id], clouds[e.object_id]
            if cache is None:
                enclosed = _encloses(a_box, b_points, cfg)
            else:
                pair, key = (e.subject_id, e.object_id), _box_key(a_box)
                was = cache.encloses.get(pair)
                enclosed = was[2] if was is not None and was[0] == key and was[1] is b_points \
                    else _encloses(a_box, b_points, cfg)
                known[pair] = (key, b_points, enclosed)
            if not enclosed:
                e = GraphEdge(subject_id=e.subject_id, predicate="on_top_of", object_id=e.object_id)
        out.append(e)
    if cache is not None:
        cache.encloses = known
    return out


def _encloses(a_box: OrientedBox, b_points: np.ndarray, cfg: RelationConfig) -> bool:
    a = _prep(a_box, cfg.min_extent_m)
    if len(b_points) == 0:
        return True
    c, s = math.cos(a.yaw), math.sin(a.yaw)
    rel = np.asarray(b_points[:, :2], dtype=np.float64) - a.center[:2]
    local = rel @ np.array([[c, -s], [s, c]])  # into a's box axes
    hx, hy = a.extent[0] / 2.0, a.extent[1] / 2.0
    z = np.asarray(b_points[:, 2], dtype=np.float64)
    over = (np.abs(local[:, 0]) <= hx) & (np.abs(local[:, 1]) <= hy) & (z > a.zmax + 0.02)
    if int(over.sum()) >= 5:
        return True
    # Walls: points beside a, above its lower third (so the surface a rests on does not count).
    band = (z > a.zmin + (a.zmax - a.zmin) / 3.0) & (z <= a.zmax + 0.1)
    sides = 0
    for axis, half in ((0, hx), (1, hy)):
        other, ohalf = 1 - axis, (hy if axis == 0 else hx)
        lateral = band & (np.abs(local[:, other]) <= ohalf)
        for sign in (1.0, -1.0):
            d = sign * local[:, axis]
            if int((lateral & (d >= half - 0.02)).sum()) >= 5:
                sides += 1
    return sides >= cfg.enclosure_min_sides
