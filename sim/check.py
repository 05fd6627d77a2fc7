"""Physical and semantic sanity checks of a scene (used by ``argus sim check`` and the tests).

* support: every object stands on the floor or on a support surface of its parent (no floating);
* interpenetration: no vertex or face centre of one object lies deeper than a tolerance inside a solid
  part of another (parts are the closed primitives an object is made of);
* relations: ``on_top_of`` children rest on a surface of their parent that a downward ray from the child
  hits; ``inside`` children lie within the parent's box;
* navigation: every room has reachable free floor in one connected component.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import trimesh

from protocol.poses import rot_z


def _point_in_quad(xy: np.ndarray, quad: np.ndarray, tol: float) -> bool:
    # quad corners in order; convex: inside if on the inner side of every edge (with tolerance)
    for k in range(4):
        a, b = quad[k], quad[(k + 1) % 4]
        e = b - a
        n = np.array([e[1], -e[0]])
        ln = float(np.linalg.norm(n))
        if ln < 1e-12:
            continue
        inner = quad.mean(axis=0) - a
        s = 1.0 if np.dot(n, inner) > 0 else -1.0
        if s * np.dot(n, xy - a) / ln < -tol:
            return False
    return True


def support_issues(scene: Any, tol_m: float = 0.01) -> list[str]:
    """Objects that float or sink: their bottom is not at the floor or at a parent support surface."""
    issues = []
    for o in scene.objects:
        zmin = float(o.mesh.bounds[0, 2])
        if o.parent_id is None:
            if abs(zmin) > tol_m:
                issues.append(f"{o.obj_id} {o.label}: bottom at z={zmin:.3f} m, not on the floor")
            continue
        try:
            p = scene.object_by_id(o.parent_id)
        except KeyError:
            issues.append(f"{o.obj_id} {o.label}: parent {o.parent_id} does not exist")
            continue
        xy = np.asarray(o.box.center[:2])
        ok = any(abs(zmin - z) <= tol_m and _point_in_quad(xy, quad, 0.01) for quad, z, _ in p.surfaces_world())
        if not ok and not p.surfaces:
            # loaded scenes without surface metadata: the child must rest on the parent's geometry
            ok = _rests_on(o, p, tol_m)
        if not ok:
            issues.append(f"{o.obj_id} {o.label}: not resting on a surface of {p.obj_id} {p.label} (z={zmin:.3f})")
    return issues


def _rests_on(child: Any, parent: Any, tol_m: float) -> bool:
    zmin = float(child.mesh.bounds[0, 2])
    c = np.asarray(child.box.center, float)
    origin = np.array([[c[0], c[1], zmin + 0.02]])
    locs, _, _ = parent.mesh.ray.intersects_location(origin, np.array([[0.0, 0.0, -1.0]]), multiple_hits=True)
    if len(locs) == 0:
        return False
    below = locs[:, 2][locs[:, 2] <= zmin + 0.02 + 1e-6]
    return len(below) > 0 and abs(float(below.max()) - zmin) <= tol_m


def _parts(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    parts = mesh.split(only_watertight=False)
    return [p for p in parts if p.is_watertight and p.volume > 1e-9]


def _depth_inside(part: trimesh.Trimesh, pts: np.ndarray) -> float:
    """Largest depth of ``pts`` inside a closed part (0 when none is inside).

    Convex parts: the exact depth is the smallest distance to a face plane. Non-convex parts (tubes):
    containment by ray parity, depth approximated by the nearest face plane (a lower bound)."""
    n = part.face_normals
    off = np.einsum("ij,ij->i", n, part.triangles[:, 0])
    s = pts @ n.T - off  # (P, F) signed plane distances, < 0 behind every face when inside
    if part.is_convex:
        d = -s.max(axis=1)
        return float(max(d.max(), 0.0))
    inside = part.contains(pts)
    if not inside.any():
        return 0.0
    return float(np.abs(s[inside]).min(axis=1).max())


def interpenetration_issues(scene: Any, tol_m: float = 0.01, max_report: int = 50) -> list[str]:
    """Pairs of objects where one's surface points lie deeper than ``tol_m`` inside the other's parts."""
    objs = scene.objects
    lo = np.array([o.mesh.bounds[0] for o in objs])
    hi = np.array([o.mesh.bounds[1] for o in objs])
    parts_cache: dict[int, list[trimesh.Trimesh]] = {}
    issues: list[str] = []
    for i in range(len(objs)):
        ov = np.all((lo[i] < hi - tol_m) & (lo + tol_m < hi[i]), axis=1)
        ov[: i + 1] = False
        for j in np.nonzero(ov)[0]:
            for a, b in ((objs[i], objs[int(j)]), (objs[int(j)], objs[i])):
                if b.obj_id not in parts_cache:
                    parts_cache[b.obj_id] = _parts(b.mesh)
                pts = np.vstack([a.mesh.vertices, a.mesh.triangles_center])
                depth = 0.0
                for part in parts_cache[b.obj_id]:
                    plo, phi = part.bounds
                    m = np.all((pts > plo + tol_m) & (pts < phi - tol_m), axis=1)
                    if not m.any():
                        continue
                    depth = max(depth, _depth_inside(part, pts[m]))
                if depth > tol_m:
                    issues.append(f"{a.obj_id} {a.label} penetrates {b.obj_id} {b.label} by {depth * 100:.1f} cm")
                    break
            if len(issues) >= max_report:
                return issues
    return issues


def relation_issues(scene: Any, tol_m: float = 0.01) -> list[str]:
    """Relations that disagree with the geometry."""
    issues = []
    ids = {o.obj_id for o in scene.objects}
    for s, pred, t in scene.relations:
        if s not in ids or t not in ids:
            issues.append(f"relation ({s}, {pred}, {t}) names a missing object")
            continue
        a, b = scene.object_by_id(s), scene.object_by_id(t)
        if pred == "on_top_of":
            if not _rests_on(a, b, tol_m):
                issues.append(f"{s} {a.label} on_top_of {t} {b.label}: no contact below the child")
        elif pred == "inside":
            c = np.asarray(a.box.center, float)
            bc = np.asarray(b.box.center, float)
            local = rot_z(-b.box.yaw_rad) @ (c - bc)
            if np.any(np.abs(local) > np.asarray(b.box.extent) / 2 + tol_m):
                issues.append(f"{s} {a.label} inside {t} {b.label}: centre outside the container's box")
        elif pred == "next_to":
            if a.room != b.room:
                issues.append(f"{s} next_to {t}: different rooms")
            d = math.dist(a.box.center[:2], b.box.center[:2])
            reach = (max(a.box.extent[:2]) + max(b.box.extent[:2])) / 2 + 0.35
            if d > reach:
                issues.append(f"{s} {a.label} next_to {t} {b.label}: {d:.2f} m apart")
        else:
            issues.append(f"unknown predicate {pred!r}")
    return issues


def nav_issues(scene: Any, nav: Any) -> list[str]:
    """Rooms without reachable free floor in the main component (so some room is cut off)."""
    issues = []
    for r in scene.rooms:
        if len(nav.room_cells(r)) == 0:
            issues.append(f"room {r.name} has no free floor reachable from the main component")
    return issues


def check_scene(scene: Any, nav: Any = None, full: bool = True) -> dict[str, list[str]]:
    """All checks; ``full=False`` skips the slower interpenetration test."""
    if nav is None:
        from sim.nav import NavMap

        nav = NavMap(scene)
    out = {
        "support": support_issues(scene),
        "relations": relation_issues(scene),
        "navigation": nav_issues(scene, nav),
    }
    if full:
        out["interpenetration"] = interpenetration_issues(scene)
    return out
