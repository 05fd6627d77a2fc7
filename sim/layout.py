"""The floor plan and the building: rooms by recursive splits of the footprint, doorways, and the
structure mesh (floors, walls with door openings, ceiling, windows) with its materials."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from sim import catalog
from sim.world import DOOR_H_M, DOOR_W_M, WALL_T_M, Door, Room

ROOM_ORDER = {
    4: ["living_room", "bedroom", "kitchen", "bathroom"],
    5: ["living_room", "bedroom", "kitchen", "office", "bathroom"],
    6: ["living_room", "bedroom", "kitchen", "bedroom", "office", "bathroom"],
    7: ["living_room", "bedroom", "kitchen", "dining_room", "bedroom", "office", "bathroom"],
    8: ["living_room", "bedroom", "kitchen", "dining_room", "bedroom", "office", "bedroom", "bathroom"],
    9: ["living_room", "bedroom", "kitchen", "dining_room", "bedroom", "office", "bedroom", "bathroom", "bathroom"],
}


@dataclass(frozen=True)
class ApartmentSpec:
    """Size of an apartment family: room counts, footprint and object count, each drawn per seed."""

    rooms: tuple[int, ...]  # room counts to draw from
    rooms_p: tuple[float, ...]  # their probabilities
    width_m: tuple[float, float]  # footprint width range (the longer side)
    width_small_m: tuple[float, float]  # width range when fewer than 5 rooms are drawn
    depth_m: tuple[float, float]  # footprint depth range
    objects: tuple[int, int]  # object count range (inclusive)


APARTMENT_SPECS: dict[str, ApartmentSpec] = {
    "apartment": ApartmentSpec((4, 5, 6), (0.15, 0.4, 0.45), (9.0, 12.5), (8.0, 10.5), (6.5, 8.5), (100, 130)),
    "apartment_large": ApartmentSpec((7, 8, 9), (0.3, 0.4, 0.3), (14.0, 18.0), (14.0, 18.0), (9.0, 11.5), (150, 190)),
}


def split_layout(rng: np.random.Generator, n_rooms: int, spec: ApartmentSpec = APARTMENT_SPECS["apartment"]
                  ) -> tuple[list[np.ndarray], list[tuple[float, float, int]], tuple[float, float]]:
    """Recursive splits of a rectangular footprint; returns room rects, doors (x, y, axis) and size."""
    for _attempt in range(50):
        W = float(rng.uniform(*spec.width_m)) if n_rooms >= 5 else float(rng.uniform(*spec.width_small_m))
        D = float(rng.uniform(*spec.depth_m))
        rects = [np.array([0.0, 0.0, W, D])]
        doors: list[tuple[float, float, int]] = []
        ok = True
        while len(rects) < n_rooms and ok:
            order = sorted(range(len(rects)), key=lambda i: -(rects[i][2] - rects[i][0]) * (rects[i][3] - rects[i][1]))
            done = False
            for i in order:
                r = rects[i]
                w, d = r[2] - r[0], r[3] - r[1]
                axes = [0, 1] if w >= d else [1, 0]
                for ax in axes:  # ax 0: split along x (vertical wall at x = c)
                    length = w if ax == 0 else d
                    if length < 2 * 2.4:
                        continue
                    f_lo, f_hi = max(0.36, 2.3 / length), min(0.64, 1.0 - 2.3 / length)
                    if f_hi <= f_lo:
                        continue
                    for _ in range(12):
                        frac = float(rng.uniform(f_lo, f_hi))
                        c = (r[0] if ax == 0 else r[1]) + frac * length
                        c = round(c, 2)
                        # doors on perpendicular walls must stay clear of the new wall
                        bad = any(dax == (0 if ax == 0 else 1) and abs((dx if ax == 0 else dy) - c) < 0.75
                                  for dx, dy, dax in doors)
                        if not bad:
                            break
                    else:
                        continue
                    if ax == 0:
                        a, b = np.array([r[0], r[1], c, r[3]]), np.array([c, r[1], r[2], r[3]])
                        lo, hi = r[1], r[3]
                    else:
                        a, b = np.array([r[0], r[1], r[2], c]), np.array([r[0], c, r[2], r[3]])
                        lo, hi = r[0], r[2]
                    p = round(float(rng.uniform(lo + 0.7, hi - 0.7)), 2)
                    # door axis: the wall runs along y for a split along x (axis 1), and vice versa
                    doors.append((c, p, 1) if ax == 0 else (p, c, 0))
                    rects[i] = a
                    rects.append(b)
                    done = True
                    break
                if done:
                    break
            ok = done
        if len(rects) == n_rooms:
            return rects, doors, (W, D)
    raise RuntimeError("room layout failed")  # pragma: no cover - 50 attempts always suffice


def build_structure(material: Callable[[str], int], rng: np.random.Generator, rects: list[np.ndarray],
                    rooms: list[Room], doors: list[Door], size: tuple[float, float], H: float
                    ) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Floor, walls with door openings, ceiling, windows; per-face material indices (``material(kind)``:
    a new material of that kind, its index)."""
    W, D = size
    t = WALL_T_M
    parts: list[tuple[trimesh.Trimesh, int | str]] = []
    room_mats: dict[str, tuple[int, int]] = {}
    for room, r in zip(rooms, rects, strict=True):
        floor_kind = "tile_floor" if room.kind in ("kitchen", "bathroom") else (
            "carpet" if room.kind == "bedroom" and rng.random() < 0.35 else "wood_floor")
        wall_kind = "tile_wall" if room.kind == "bathroom" else "paint"
        room_mats[room.name] = (material(floor_kind), material(wall_kind))
        parts.append((catalog.box(r[2] - r[0], r[3] - r[1], 0.05, (r[0] + r[2]) / 2, (r[1] + r[3]) / 2, -0.05),
                      room_mats[room.name][0]))
    ceiling = material("ceiling")
    parts.append((catalog.box(W + t, D + t, 0.05, W / 2, D / 2, H), ceiling))
    # wall segments: exterior boundary plus every shared edge between rects, minus door gaps
    segs: list[tuple[int, float, float, float]] = []  # (axis, fixed coord, lo, hi); axis 0: runs along x
    segs += [(0, 0.0, -t / 2, W + t / 2), (0, D, -t / 2, W + t / 2), (1, 0.0, 0.0, D), (1, W, 0.0, D)]
    interior: set[tuple[int, float, float, float]] = set()
    for i, a in enumerate(rects):
        for bb in rects[i + 1:]:
            for ax in (0, 1):
                if ax == 1:  # vertical shared edge at x
                    for xa, xb in ((a[2], bb[0]), (a[0], bb[2])):
                        if abs(xa - xb) < 1e-6:
                            lo, hi = max(a[1], bb[1]), min(a[3], bb[3])
                            if hi - lo > 1e-6:
                                interior.add((1, round(xa, 4), round(lo, 4), round(hi, 4)))
                else:
                    for ya, yb in ((a[3], bb[1]), (a[1], bb[3])):
                        if abs(ya - yb) < 1e-6:
                            lo, hi = max(a[0], bb[0]), min(a[2], bb[2])
                            if hi - lo > 1e-6:
                                interior.add((0, round(ya, 4), round(lo, 4), round(hi, 4)))
    segs += sorted(interior)
    wall_parts: list[trimesh.Trimesh] = []
    for ax, c, lo, hi in segs:
        cuts = sorted(
            (float(d.center_xy[0] if ax == 0 else d.center_xy[1]), d.width_m) for d in doors
            if d.axis == ax and abs((d.center_xy[1] if ax == 0 else d.center_xy[0]) - c) < 1e-6
            and lo < (d.center_xy[0] if ax == 0 else d.center_xy[1]) < hi
        )
        pos = lo
        pieces = []
        for p, w in cuts:
            pieces.append((pos, p - w / 2, 0.0, H))
            pieces.append((p - w / 2, p + w / 2, DOOR_H_M, H))  # lintel
            pos = p + w / 2
        pieces.append((pos, hi, 0.0, H))
        for a0, a1, z0, z1 in pieces:
            if a1 - a0 < 1e-6:
                continue
            if ax == 0:
                m = catalog.box(a1 - a0, t, z1 - z0, (a0 + a1) / 2, c, z0)
            else:
                m = catalog.box(t, a1 - a0, z1 - z0, c, (a0 + a1) / 2, z0)
            wall_parts.append(m)
    # windows on exterior walls: a glass pane just inside the wall face
    win = material("window")
    frame = material("white")
    for room, r in zip(rooms, rects, strict=True):
        sides = []
        if r[1] < 1e-6:
            sides.append((0, r[1] + t / 2 + 0.004, r[0], r[2]))
        if r[3] > D - 1e-6:
            sides.append((0, r[3] - t / 2 - 0.004, r[0], r[2]))
        if r[0] < 1e-6:
            sides.append((1, r[0] + t / 2 + 0.004, r[1], r[3]))
        if r[2] > W - 1e-6:
            sides.append((1, r[2] - t / 2 - 0.004, r[1], r[3]))
        if not sides or room.kind == "bathroom":
            continue
        ax, c, lo, hi = sides[int(rng.integers(len(sides)))]
        ww = min(1.4, (hi - lo) - 1.2)
        if ww < 0.6:
            continue
        mid = (lo + hi) / 2
        for m, k in ((catalog.box(ww + 0.08, 0.006, 1.38, mid, c, 0.86) if ax == 0
                      else catalog.box(0.006, ww + 0.08, 1.38, c, mid, 0.86), frame),
                     (catalog.box(ww, 0.008, 1.3, mid, c, 0.9) if ax == 0
                      else catalog.box(0.008, ww, 1.3, c, mid, 0.9), win)):
            parts.append((m, k))
    meshes = [m for m, _ in parts] + wall_parts
    fmat = [np.full(len(m.faces), k, np.int32) for m, k in parts]
    # wall faces take the material of the room they face
    neutral = material("paint")
    for m in wall_parts:
        fm = np.full(len(m.faces), neutral, np.int32)
        cen = m.triangles_center + m.face_normals * 0.06
        for fi, (x, y, _) in enumerate(cen):
            for room in rooms:
                if room.contains(x, y):
                    fm[fi] = room_mats[room.name][1]
                    break
        fmat.append(fm)
    mesh = catalog.concat(meshes)
    return mesh, np.concatenate(fmat)


@dataclass(frozen=True)
class FloorPlan:
    """A drawn floor plan: room rectangles, doorways and the object count to furnish it with."""

    rects: list[np.ndarray]  # per room (x0, y0, x1, y1) on the wall centre lines
    doors: list[tuple[float, float, int]]  # doorway centres (x, y) and wall axis (0: the wall runs along x)
    size: tuple[float, float]  # footprint (W, D)
    kinds: list[str]  # room kind per rectangle
    n_objects: int  # objects to place (furniture and items)


def draw_floor_plan(rng: np.random.Generator, family: str) -> FloorPlan:
    """An apartment family's rooms by recursive splits of the footprint (the largest rooms get the first
    kinds of ``ROOM_ORDER``), or the one room of ``furnished_room``; and the object count."""
    rects: list[np.ndarray]
    raw_doors: list[tuple[float, float, int]]
    if family in APARTMENT_SPECS:
        spec = APARTMENT_SPECS[family]
        n_rooms = int(rng.choice(list(spec.rooms), p=list(spec.rooms_p)))
        rects, raw_doors, size = split_layout(rng, n_rooms, spec)
        areas = [(r[2] - r[0]) * (r[3] - r[1]) for r in rects]
        order = np.argsort(areas)[::-1]
        kinds = [""] * n_rooms
        for rank, idx in enumerate(order):
            kinds[int(idx)] = ROOM_ORDER[n_rooms][rank]
        target = int(rng.integers(spec.objects[0], spec.objects[1] + 1))
    else:
        W, D = float(rng.uniform(4.5, 6.5)), float(rng.uniform(4.0, 5.5))
        rects, raw_doors, size = [np.array([0.0, 0.0, W, D])], [], (W, D)
        kinds = [str(rng.choice(["living_room", "bedroom", "office", "dining_room", "kitchen"]))]
        target = int(rng.integers(20, 31))
    return FloorPlan(rects, raw_doors, size, kinds, target)


def name_rooms(kinds: list[str], rects: list[np.ndarray]) -> list[Room]:
    """The rooms: named by kind (numbered when a kind repeats), their free floor inside the walls."""
    names: list[str] = []
    counts: dict[str, int] = {}
    for k in kinds:
        counts[k] = counts.get(k, 0) + 1
    seen: dict[str, int] = {}
    for k in kinds:
        seen[k] = seen.get(k, 0) + 1
        names.append(f"{k}_{seen[k]}" if counts[k] > 1 else k)
    t = WALL_T_M / 2
    return [Room(n, k, np.array([r[0] + t, r[1] + t]), np.array([r[2] - t, r[3] - t]))
            for n, k, r in zip(names, kinds, rects, strict=True)]


def connect_rooms(raw_doors: list[tuple[float, float, int]], rooms: list[Room]) -> list[Door]:
    """Each doorway with the two rooms it joins."""
    doors = []
    for x, y, ax in raw_doors:
        off = np.array([0.0, 0.3]) if ax == 0 else np.array([0.3, 0.0])
        ra = next(r.name for r in rooms if r.contains(*(np.array([x, y]) - off)))
        rb = next(r.name for r in rooms if r.contains(*(np.array([x, y]) + off)))
        doors.append(Door(np.array([x, y]), ax, DOOR_W_M, (ra, rb)))
    return doors
