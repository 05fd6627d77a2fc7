"""Ground-truth relations between a scene's objects: support (``on_top_of`` / ``inside``) as the generator
placed them, ``next_to`` from the objects' footprints."""

from __future__ import annotations

import math

import numpy as np

from protocol.messages import OrientedBox
from protocol.poses import rot_z
from sim.world import SceneObject


def _rect_gap(a: OrientedBox, b: OrientedBox) -> float:
    """Horizontal gap between two boxes' footprints (0 when they overlap), exact for rotated rectangles."""

    def corners(bx: OrientedBox) -> np.ndarray:
        ex, ey = bx.extent[0] / 2, bx.extent[1] / 2
        c = np.array([[-ex, -ey], [ex, -ey], [ex, ey], [-ex, ey]])
        return c @ rot_z(bx.yaw_rad)[:2, :2].T + np.array(bx.center[:2])

    ca, cb = corners(a), corners(b)

    def separated(p: np.ndarray, q: np.ndarray) -> bool:
        for poly in (p, q):
            for k in range(4):
                e = poly[(k + 1) % 4] - poly[k]
                nrm = np.array([-e[1], e[0]])
                if (p @ nrm).max() < (q @ nrm).min() or (q @ nrm).max() < (p @ nrm).min():
                    return True
        return False

    if not separated(ca, cb):
        return 0.0

    def pt_seg(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> float:
        d = s1 - s0
        t = float(np.clip(np.dot(p - s0, d) / max(np.dot(d, d), 1e-12), 0.0, 1.0))
        return float(np.linalg.norm(p - (s0 + t * d)))

    best = math.inf
    for p, q in ((ca, cb), (cb, ca)):
        for v in p:
            for k in range(4):
                best = min(best, pt_seg(v, q[k], q[(k + 1) % 4]))
    return best


def compute_relations(objects: list[SceneObject], support_kinds: list[str | None] | None = None
                      ) -> list[tuple[int, str, int]]:
    """Ground-truth relations: support (on_top_of / inside) from the generator, next_to from geometry.

    ``next_to`` links objects in the same room with the same support parent whose footprints are within
    0.3 m (furniture) or 0.12 m (items) and whose height ranges overlap; listed once per unordered pair
    (smaller id first): the predicate is symmetric.
    """
    rel: list[tuple[int, str, int]] = []
    for i, o in enumerate(objects):
        if o.parent_id is not None:
            kind = support_kinds[i] if support_kinds else "on"
            rel.append((o.obj_id, "inside" if kind == "in" else "on_top_of", o.parent_id))
    groups: dict[tuple[str, int | None], list[SceneObject]] = {}
    for o in objects:
        if o.box.extent[2] < 0.03 and o.parent_id is None:  # rugs and mats are not neighbours
            continue
        groups.setdefault((o.room, o.parent_id), []).append(o)
    for (_room, parent), objs in groups.items():
        thr = 0.3 if parent is None else 0.12
        for a_i in range(len(objs)):
            a = objs[a_i]
            for b_o in objs[a_i + 1:]:
                za = (a.box.center[2] - a.box.extent[2] / 2, a.box.center[2] + a.box.extent[2] / 2)
                zb = (b_o.box.center[2] - b_o.box.extent[2] / 2, b_o.box.center[2] + b_o.box.extent[2] / 2)
                if za[1] < zb[0] or zb[1] < za[0]:
                    continue
                ra = max(a.box.extent[0], a.box.extent[1]) / 2 + max(b_o.box.extent[0], b_o.box.extent[1]) / 2
                if np.hypot(a.box.center[0] - b_o.box.center[0], a.box.center[1] - b_o.box.center[1]) > ra + thr:
                    continue
                if _rect_gap(a.box, b_o.box) <= thr:
                    lo, hi = sorted((a.obj_id, b_o.obj_id))
                    rel.append((lo, "next_to", hi))
    return rel
