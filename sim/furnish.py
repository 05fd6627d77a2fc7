"""Furnishing: furniture per room by the room kind's plan (wall, corner, centre and anchored rules, door
keep-outs, a walkable floor kept connected), then small items on and in the furniture's support surfaces."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage

from protocol.messages import OrientedBox, vec3
from protocol.poses import rot_z
from sim import catalog
from sim.catalog import CATEGORIES, Model
from sim.materials import Material, make_material
from sim.world import Door, Room, SceneObject

# Furniture plans per room kind: (category, rule, probability). Rules: wall, corner, center,
# front:<anchor>, beside:<anchor>, opposite:<anchor>, under:<anchor>, around:<anchor>.
_PLANS: dict[str, list[tuple[str, str, float]]] = {
    "living_room": [
        ("sofa", "wall", 1.0), ("coffee_table", "front:sofa", 1.0), ("rug", "under:coffee_table", 0.8),
        ("tv_stand", "opposite:sofa", 0.95), ("side_table", "beside:sofa", 0.7), ("armchair", "wall", 0.7),
        ("bookshelf", "wall", 0.85), ("floor_lamp", "corner", 0.7), ("potted_plant", "corner", 0.9),
        ("dining_table", "center", 0.45), ("dining_chair", "around:dining_table", 1.0),
        ("potted_plant", "corner", 0.4),
    ],
    "kitchen": [
        ("refrigerator", "corner", 1.0), ("kitchen_sink", "wall", 1.0), ("stove", "wall", 1.0),
        ("kitchen_counter", "wall", 1.0), ("kitchen_counter", "wall", 0.6), ("trash_can", "corner", 0.8),
        ("dining_table", "center", 0.5), ("dining_chair", "around:dining_table", 1.0),
        ("kitchen_island", "center", 0.5), ("bar_stool", "around:kitchen_island", 1.0),
    ],
    "bedroom": [
        ("bed", "wall", 1.0), ("nightstand", "beside:bed", 1.0), ("nightstand", "beside:bed", 0.7),
        ("wardrobe", "wall", 0.9), ("dresser", "wall", 0.7), ("chair", "wall", 0.4),
        ("laundry_basket", "corner", 0.6), ("potted_plant", "corner", 0.4), ("rug", "center", 0.3),
    ],
    "bathroom": [
        ("bathtub", "corner", 0.9), ("toilet", "wall", 1.0), ("bathroom_sink", "wall", 1.0),
        ("bath_mat", "front:bathtub", 0.8), ("laundry_basket", "corner", 0.5), ("trash_can", "corner", 0.6),
    ],
    "office": [
        ("desk", "wall", 1.0), ("office_chair", "front:desk", 1.0), ("bookshelf", "wall", 1.0),
        ("filing_cabinet", "beside:desk", 0.8), ("bookshelf", "wall", 0.5), ("potted_plant", "corner", 0.6),
        ("armchair", "wall", 0.4), ("trash_can", "corner", 0.5),
    ],
    "dining_room": [
        ("dining_table", "center", 1.0), ("dining_chair", "around:dining_table", 1.0),
        ("dresser", "wall", 0.9), ("bookshelf", "wall", 0.7), ("potted_plant", "corner", 0.9),
        ("floor_lamp", "corner", 0.6), ("armchair", "wall", 0.5), ("potted_plant", "corner", 0.5),
    ],
}

# Items per support category: (item category, weight). "!" marks the first choice made for every parent.
_ITEMS: dict[str, list[tuple[str, float]]] = {
    "sofa": [("!pillow", 1.0), ("pillow", 1.0)],
    "armchair": [("pillow", 1.0)],
    "coffee_table": [("book", 1.0), ("magazine", 1.0), ("remote_control", 1.0), ("vase", 0.6), ("candle", 0.6),
                     ("mug", 0.6), ("fruit_bowl", 0.4), ("small_plant", 0.5), ("tissue_box", 0.4)],
    "side_table": [("!table_lamp", 1.0), ("book", 0.6), ("cup", 0.4), ("small_plant", 0.4)],
    "dining_table": [("plate", 1.0), ("bowl", 0.6), ("cup", 0.6), ("wine_glass", 0.5), ("fruit_bowl", 0.6),
                     ("vase", 0.5), ("wine_bottle", 0.4), ("bottle", 0.3)],
    "desk": [("!monitor", 0.7), ("laptop", 0.6), ("keyboard", 0.6), ("computer_mouse", 0.6),
             ("desk_lamp", 0.8), ("mug", 0.6), ("notebook", 0.7), ("pen_holder", 0.6), ("book", 0.5),
             ("headphones", 0.3), ("globe", 0.2)],
    "bookshelf": [("standing_book", 4.0), ("storage_box", 0.6), ("picture_frame", 0.4), ("vase", 0.3),
                  ("basket", 0.3), ("small_plant", 0.3), ("clock", 0.2)],
    "tv_stand": [("!television", 1.0), ("speaker", 0.6), ("small_plant", 0.5), ("picture_frame", 0.5),
                 ("book", 0.3), ("remote_control", 0.3), ("storage_box", 0.3)],
    "kitchen_counter": [("!kettle", 1.0), ("toaster", 0.7), ("coffee_maker", 0.7), ("microwave", 0.9),
                        ("cutting_board", 0.8), ("bowl", 0.6), ("bottle", 0.6), ("wine_bottle", 0.3),
                        ("fruit_bowl", 0.5), ("cooking_pot", 0.4), ("mug", 0.5), ("plate", 0.4)],
    "kitchen_sink": [("!bowl", 1.0), ("plate", 0.8), ("cup", 0.6), ("mug", 0.5), ("soap_dispenser", 0.8)],
    "stove": [("!cooking_pot", 1.0), ("frying_pan", 0.8)],
    "kitchen_island": [("fruit_bowl", 0.8), ("bowl", 0.5), ("cutting_board", 0.5), ("bottle", 0.5),
                       ("vase", 0.4)],
    "refrigerator": [("basket", 0.3), ("storage_box", 0.3)],
    "bed": [("!pillow", 1.0), ("pillow", 1.0), ("blanket", 0.3)],
    "nightstand": [("!table_lamp", 1.0), ("alarm_clock", 0.7), ("book", 0.6), ("cup", 0.3),
                   ("small_plant", 0.3)],
    "dresser": [("picture_frame", 0.7), ("vase", 0.5), ("storage_box", 0.5), ("book", 0.4), ("clock", 0.4),
                ("small_plant", 0.4), ("basket", 0.3)],
    "filing_cabinet": [("!printer", 0.8), ("storage_box", 0.3), ("small_plant", 0.3)],
    "bathroom_sink": [("!soap_dispenser", 1.0), ("toothbrush_holder", 1.0), ("towel", 0.6),
                      ("tissue_box", 0.3)],
    "toilet": [("!toilet_paper", 1.0)],
    "bathtub": [("shampoo_bottle", 0.8), ("towel", 0.3)],
    "laundry_basket": [("towel", 1.0)],
    "fruit_bowl": [("!apple", 1.0), ("apple", 1.0), ("orange", 1.0)],
    "basket": [("towel", 0.3)],
    "chair": [("backpack", 0.5)],
    "dining_chair": [],
}
# Appliances and screens a room has at most one of.
_ONE_PER_ROOM = {"television", "kettle", "toaster", "coffee_maker", "microwave", "printer", "monitor", "laptop",
                 "keyboard", "computer_mouse", "globe", "alarm_clock", "clock", "frying_pan"}
# Items that face the front of their support (screens, frames, appliances).
_FACING = {"television", "monitor", "laptop", "keyboard", "picture_frame", "speaker", "microwave", "alarm_clock",
           "clock", "coffee_maker", "printer", "toaster"}
# Items big enough for the furnished_room family ("larger objects").
_LARGE_ITEMS = {"television", "monitor", "laptop", "table_lamp", "desk_lamp", "pillow", "microwave", "kettle",
                "coffee_maker", "toaster", "vase", "printer", "speaker", "storage_box", "fruit_bowl", "blanket",
                "cooking_pot", "globe", "basket", "backpack", "small_plant", "towel", "picture_frame", "book",
                "cutting_board", "bowl", "standing_book", "alarm_clock", "wine_bottle", "plate", "laundry_basket"}


@dataclass
class _Placed:
    """Generation-time record of one object."""

    cat: str
    model: Model
    T: np.ndarray
    room: str
    parent: int | None  # index into the placed list
    surface_kind: str | None
    rect: tuple[float, float, float, float] | None  # world footprint AABB (furniture)
    z_limit: float  # nothing may stand above this height on it
    mats: dict[str, int]


def _local_bounds(model: Model) -> np.ndarray:
    return model.bounds


def _pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_z(yaw)
    T[:3, 3] = (x, y, z)
    return T


def _footprint(model: Model, T: np.ndarray) -> tuple[float, float, float, float]:
    b = _local_bounds(model)
    c = np.array([[b[0, 0], b[0, 1]], [b[1, 0], b[0, 1]], [b[1, 0], b[1, 1]], [b[0, 0], b[1, 1]]])
    w = c @ T[:2, :2].T + T[:2, 3]
    return float(w[:, 0].min()), float(w[:, 1].min()), float(w[:, 0].max()), float(w[:, 1].max())


def _rects_overlap(a: tuple[float, ...], b: tuple[float, ...], pad: float = 0.0) -> bool:
    return a[0] < b[2] + pad and b[0] < a[2] + pad and a[1] < b[3] + pad and b[1] < a[3] + pad


class _RoomPlanner:
    """Places furniture in one room: wall / corner / centre rules, door keep-outs, nav connectivity."""

    CELL = 0.1
    RADIUS = 0.3

    def __init__(self, room: Room, doors: list[Door], rng: np.random.Generator):
        self.room = room
        self.rng = rng
        self.rects: list[tuple[float, float, float, float]] = []
        self.keepout: list[tuple[float, float, float, float]] = []
        self.approach: list[tuple[float, float]] = []
        self.doors = [d for d in doors if room.name in d.rooms]
        x0, y0 = room.xy_min
        x1, y1 = room.xy_max
        for d in self.doors:
            cx, cy = d.center_xy
            hw = d.width_m / 2 + 0.2
            if d.axis == 0:  # wall along x; room is above or below
                inside = 1.0 if cy < (y0 + y1) / 2 else -1.0
                self.keepout.append((cx - hw, min(cy, cy + inside * 1.0), cx + hw, max(cy, cy + inside * 1.0)))
                self.approach.append((cx, cy + inside * 0.45))
            else:
                inside = 1.0 if cx < (x0 + x1) / 2 else -1.0
                self.keepout.append((min(cx, cx + inside * 1.0), cy - hw, max(cx, cx + inside * 1.0), cy + hw))
                self.approach.append((cx + inside * 0.45, cy))
        nx = int(math.ceil((x1 - x0) / self.CELL))
        ny = int(math.ceil((y1 - y0) / self.CELL))
        self.shape = (ny + 2, nx + 2)  # one-cell wall ring
        self.base = np.zeros(self.shape, bool)
        self.base[0, :] = self.base[-1, :] = True
        self.base[:, 0] = self.base[:, -1] = True
        for d in self.doors:  # open the ring at doorways
            cx, cy = d.center_xy
            if d.axis == 0:
                i0, i1 = self._ix(cx - d.width_m / 2 + 0.05), self._ix(cx + d.width_m / 2 - 0.05)
                row = 0 if cy < (y0 + y1) / 2 else self.shape[0] - 1
                self.base[row, max(i0, 1):min(i1, self.shape[1] - 1)] = False
            else:
                j0, j1 = self._iy(cy - d.width_m / 2 + 0.05), self._iy(cy + d.width_m / 2 - 0.05)
                col = 0 if cx < (x0 + x1) / 2 else self.shape[1] - 1
                self.base[max(j0, 1):min(j1, self.shape[0] - 1), col] = False

    def _ix(self, x: float) -> int:
        return int(math.floor((x - self.room.xy_min[0]) / self.CELL)) + 1

    def _iy(self, y: float) -> int:
        return int(math.floor((y - self.room.xy_min[1]) / self.CELL)) + 1

    def _grid(self, rects: list[tuple[float, float, float, float]]) -> np.ndarray:
        g = self.base.copy()
        for r in rects:
            i0, i1 = max(self._ix(r[0]), 1), min(self._ix(r[2]) + 1, self.shape[1] - 1)
            j0, j1 = max(self._iy(r[1]), 1), min(self._iy(r[3]) + 1, self.shape[0] - 1)
            g[j0:j1, i0:i1] = True
        return g

    def connected_ok(self, rects: list[tuple[float, float, float, float]]) -> bool:
        free = ndimage.distance_transform_edt(~self._grid(rects)) * self.CELL > self.RADIUS
        lab, n = ndimage.label(free)
        if n == 0:
            return False
        sizes = np.bincount(lab.ravel())
        sizes[0] = 0
        main = int(np.argmax(sizes))
        if sizes[main] < 0.5 * free.sum():
            return False
        for ax, ay in self.approach:
            j, i = self._iy(ay), self._ix(ax)
            if not (0 <= j < self.shape[0] and 0 <= i < self.shape[1]) or lab[j, i] != main:
                return False
        return True

    def fits(self, rect: tuple[float, float, float, float], flat: bool = False, pad: float = 0.04) -> bool:
        x0, y0 = self.room.xy_min
        x1, y1 = self.room.xy_max
        eps = 1e-6
        if rect[0] < x0 - eps or rect[1] < y0 - eps or rect[2] > x1 + eps or rect[3] > y1 + eps:
            return False
        if flat:
            return True
        if any(_rects_overlap(rect, k) for k in self.keepout):
            return False
        if any(_rects_overlap(rect, r, pad) for r in self.rects):
            return False
        return self.connected_ok([*self.rects, rect])

    def wall_pose(self, model: Model, side: int, t: float, gap: float = 0.02) -> np.ndarray:
        """Pose of ``model`` backed against wall ``side`` (0 S, 1 N, 2 W, 3 E) at fraction t along it."""
        yaw = (0.0, math.pi, -math.pi / 2, math.pi / 2)[side]
        T0 = _pose(0, 0, 0, yaw)
        fx0, fy0, fx1, fy1 = _footprint(model, T0)
        x0, y0 = self.room.xy_min
        x1, y1 = self.room.xy_max
        if side in (0, 1):
            lo, hi = x0 - fx0, x1 - fx1
            x = lo + t * max(hi - lo, 0.0)
            y = y0 + gap - fy0 if side == 0 else y1 - gap - fy1
        else:
            lo, hi = y0 - fy0, y1 - fy1
            y = lo + t * max(hi - lo, 0.0)
            x = x0 + gap - fx0 if side == 2 else x1 - gap - fx1
        return _pose(x, y, 0.0, yaw)

    def side_of(self, T: np.ndarray) -> int:
        yaw = math.atan2(T[1, 0], T[0, 0])
        k = int(round(yaw / (math.pi / 2))) % 4  # 0 -> yaw 0 (S), 1 -> +90 (E), 2 -> 180 (N), 3 -> -90 (W)
        return {0: 0, 1: 3, 2: 1, 3: 2}[k]


class Builder:
    """Accumulates materials and objects while a scene is generated."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.materials: list[Material] = []
        self.placed: list[_Placed] = []

    def material(self, kind: str) -> int:
        self.materials.append(make_material(kind, self.rng))
        return len(self.materials) - 1

    def mats_for(self, model: Model) -> dict[str, int]:
        kinds = sorted({k for _, k in model.parts})
        return {k: self.material(k) for k in kinds}


def place_furniture(b: Builder, room: Room, doors: list[Door], plan: list[tuple[str, str, float]],
                     wall_h: float) -> None:
    rng = b.rng
    rp = _RoomPlanner(room, doors, rng)
    by_cat: dict[str, list[int]] = {}
    for cat, rule, prob in plan:
        if rng.random() >= prob:
            continue
        kind, _, anchor = rule.partition(":")
        if anchor and anchor not in by_cat:
            continue
        model = CATEGORIES[cat].build(rng)
        flat = cat in ("rug", "bath_mat")
        candidates: list[np.ndarray] = []
        if kind in ("wall", "corner"):
            for _ in range(14):
                side = int(rng.integers(4))
                t = float(rng.choice([0.0, 1.0])) if kind == "corner" else float(rng.uniform(0.0, 1.0))
                candidates.append(rp.wall_pose(model, side, t))
        elif kind == "center":
            c = (room.xy_min + room.xy_max) / 2
            for _ in range(10):
                yaw = float(rng.choice([0.0, math.pi / 2]))
                j = rng.uniform(-0.6, 0.6, 2)
                candidates.append(_pose(c[0] + j[0], c[1] + j[1], 0.0, yaw))
        elif kind in ("front", "beside", "opposite", "under"):
            a = b.placed[by_cat[anchor][-1]]
            ab = _local_bounds(a.model)
            mb = _local_bounds(model)
            Ta = a.T
            if kind == "front":
                gap = 0.45 if cat == "coffee_table" else 0.08
                face = cat in ("office_chair",)
                yaw_rel = math.pi if face else 0.0
                y_local = ab[1, 1] + gap + (mb[1, 1] if face else -mb[0, 1])
                for dx in (0.0, 0.1, -0.1, 0.2, -0.2):
                    p = Ta @ np.array([dx, y_local, 0.0, 1.0])
                    yaw = math.atan2(Ta[1, 0], Ta[0, 0]) + yaw_rel
                    candidates.append(_pose(p[0], p[1], 0.0, yaw))
            elif kind == "beside":
                for sgn in ((1, -1) if rng.random() < 0.5 else (-1, 1)):
                    x_local = (ab[1, 0] + 0.05 - mb[0, 0]) if sgn > 0 else (ab[0, 0] - 0.05 - mb[1, 0])
                    y_local = ab[0, 1] - mb[0, 1]
                    p = Ta @ np.array([x_local, y_local, 0.0, 1.0])
                    candidates.append(_pose(p[0], p[1], 0.0, math.atan2(Ta[1, 0], Ta[0, 0])))
            elif kind == "opposite":
                side = {0: 1, 1: 0, 2: 3, 3: 2}[rp.side_of(Ta)]
                for _ in range(8):
                    candidates.append(rp.wall_pose(model, side, float(rng.uniform(0.25, 0.75))))
            else:  # under
                p = Ta[:3, 3]
                candidates.append(_pose(p[0], p[1], 0.0, math.atan2(Ta[1, 0], Ta[0, 0])))
        elif kind == "around":
            a = b.placed[by_cat[anchor][-1]]
            ab = _local_bounds(a.model)
            Ta = a.T
            yaw_a = math.atan2(Ta[1, 0], Ta[0, 0])
            n_side = 2 if ab[1, 0] - ab[0, 0] > 1.3 else 1
            for sgn in (1, -1):
                for k in range(n_side):
                    m2 = CATEGORIES[cat].build(rng)
                    mb = _local_bounds(m2)
                    xl = 0.0 if n_side == 1 else (k - 0.5) * (ab[1, 0] - ab[0, 0]) / 2
                    yl = sgn * (ab[1, 1] + 0.1 - mb[0, 1])  # chair back away from the table
                    p = Ta @ np.array([xl, yl, 0.0, 1.0])
                    T = _pose(p[0], p[1], 0.0, yaw_a + (0.0 if sgn > 0 else math.pi))
                    rect = _footprint(m2, T)
                    if rp.fits(rect, pad=0.02):
                        rp.rects.append(rect)
                        b.placed.append(_Placed(cat, m2, T, room.name, None, None, rect, wall_h, b.mats_for(m2)))
                        by_cat.setdefault(cat, []).append(len(b.placed) - 1)
            continue
        for T in candidates:
            rect = _footprint(model, T)
            if rp.fits(rect, flat=flat):
                if not flat:
                    rp.rects.append(rect)
                b.placed.append(_Placed(cat, model, T, room.name, None, None, rect, wall_h, b.mats_for(model)))
                by_cat.setdefault(cat, []).append(len(b.placed) - 1)
                break


def _try_place_item(b: Builder, parent_idx: int, cat: str, occupied: dict[tuple[int, int], list]) -> bool:
    """Put one ``cat`` item on a free spot of a support surface of placed object ``parent_idx``."""
    rng = b.rng
    parent = b.placed[parent_idx]
    surfaces = parent.model.surfaces
    if not surfaces:
        return False
    if cat in _ONE_PER_ROOM and any(p.cat == cat and p.room == parent.room for p in b.placed):
        return False
    model = CATEGORIES[cat].build(rng)
    mb = _local_bounds(model)
    h = float(mb[1, 2] - mb[0, 2])
    order = rng.permutation(len(surfaces))
    for si in order:
        s = surfaces[int(si)]
        z_world = float((parent.T @ np.array([0, 0, s.z, 1.0]))[2])
        clear = min(s.clear_m, parent.z_limit - z_world)
        if h > clear - 0.005:
            continue
        key = (parent_idx, int(si))
        occ = occupied.setdefault(key, [])
        shelf_row = s.kind == "in" and parent.cat == "bookshelf"
        for _ in range(10 if not shelf_row else 6):
            if cat in ("standing_book",):
                yaw_l = 0.0
            elif cat in _FACING:
                yaw_l = float(rng.uniform(-0.1, 0.1))
            elif shelf_row or s.kind == "in" and s.x1 - s.x0 < 0.4:
                yaw_l = float(rng.uniform(-0.15, 0.15))
            else:
                yaw_l = float(rng.choice([0.0, math.pi / 2, math.pi, -math.pi / 2]) + rng.uniform(-0.35, 0.35))
            R = rot_z(yaw_l)[:2, :2]
            c = np.array([[mb[0, 0], mb[0, 1]], [mb[1, 0], mb[0, 1]], [mb[1, 0], mb[1, 1]], [mb[0, 0], mb[1, 1]]])
            rc = c @ R.T
            lo, hi = rc.min(0), rc.max(0)
            xr = (s.x0 - lo[0], s.x1 - hi[0])
            yr = (s.y0 - lo[1], s.y1 - hi[1])
            if xr[1] < xr[0] or yr[1] < yr[0]:
                break
            if cat == "standing_book" and occ:  # books stand in a row, left to right
                x = max(r[2] for r in occ) + 0.002 - lo[0] + float(rng.uniform(0.0, 0.01))
                if x > xr[1]:
                    break
                y = yr[0] + float(rng.uniform(0, max(0.0, min(0.04, yr[1] - yr[0]))))
            else:
                x = float(rng.uniform(*xr))
                y = float(rng.uniform(*yr))
            rect = (x + lo[0], y + lo[1], x + hi[0], y + hi[1])
            if any(_rects_overlap(rect, r, 0.0 if cat == "standing_book" else 0.01) for r in occ):
                continue
            occ.append(rect)
            T_local = _pose(x, y, s.z - mb[0, 2], yaw_l)
            T = parent.T @ T_local
            b.placed.append(_Placed(cat, model, T, parent.room, parent_idx, s.kind, None,
                                    z_world + clear, b.mats_for(model)))
            return True
    return False


def fill_items(b: Builder, target: int, large_only: bool) -> None:
    rng = b.rng
    occupied: dict[tuple[int, int], list] = {}

    def choices(cat: str) -> list[tuple[str, float]]:
        out = []
        for c, w in _ITEMS.get(cat, []):
            c = c.lstrip("!")
            if large_only and c not in _LARGE_ITEMS:
                continue
            out.append((c, w))
        return out

    # mandatory first items
    i = 0
    while i < len(b.placed) and len(b.placed) < target:
        p = b.placed[i]
        for c, _w in _ITEMS.get(p.cat, []):
            if c.startswith("!") and (not large_only or c[1:] in _LARGE_ITEMS):
                _try_place_item(b, i, c[1:], occupied)
        i += 1
    # then random fill until the target count, weighting parents by their surface area
    failures = 0
    while len(b.placed) < target and failures < 400:
        hosts = [k for k, p in enumerate(b.placed) if p.model.surfaces and choices(p.cat)]
        if not hosts:
            break
        # balance rooms first (so a bookshelf-heavy office does not take every item), then surface area
        host_rooms = sorted({b.placed[k].room for k in hosts})
        room = host_rooms[int(rng.integers(len(host_rooms)))]
        hosts = [k for k in hosts if b.placed[k].room == room]
        area = np.array([sum((s.x1 - s.x0) * (s.y1 - s.y0) * (0.35 if s.kind == "in" else 1.0)
                             for s in b.placed[k].model.surfaces) + 0.05 for k in hosts])
        k = hosts[int(rng.choice(len(hosts), p=area / area.sum()))]
        opts = choices(b.placed[k].cat)
        w = np.array([x[1] for x in opts])
        cat = opts[int(rng.choice(len(opts), p=w / w.sum()))][0]
        if cat == "standing_book":  # a run of books on one shelf
            n_ok = sum(_try_place_item(b, k, cat, occupied) for _ in range(int(rng.integers(2, 5)))
                       if len(b.placed) < target)
            failures += n_ok == 0
        elif not _try_place_item(b, k, cat, occupied):
            failures += 1


# The furnished_room family's one room gets more furniture than its kind's plan.
_FURNISHED_ROOM_EXTRA: list[tuple[str, str, float]] = [
    ("potted_plant", "corner", 0.7), ("floor_lamp", "corner", 0.6), ("bookshelf", "wall", 0.6),
    ("armchair", "wall", 0.5), ("side_table", "wall", 0.6), ("dresser", "wall", 0.5),
    ("trash_can", "corner", 0.5), ("chair", "wall", 0.4), ("potted_plant", "corner", 0.5),
]


def furniture_plan(kind: str, family: str) -> list[tuple[str, str, float]]:
    """The furniture plan of a room of ``kind`` in a scene of ``family``: (category, rule, probability)."""
    return list(_PLANS[kind]) + (_FURNISHED_ROOM_EXTRA if family == "furnished_room" else [])


def scene_objects(b: Builder) -> list[SceneObject]:
    """The placed objects as ground-truth objects: world meshes with per-face materials, oriented boxes,
    ids from 1 in placement order (the renders' instance ids), support parents."""
    objects: list[SceneObject] = []
    for i, p in enumerate(b.placed):
        meshes, fmats = [], []
        R, t = p.T[:3, :3], p.T[:3, 3]
        for m, kind in p.model.parts:
            mm = trimesh.Trimesh(vertices=np.asarray(m.vertices) @ R.T + t, faces=np.asarray(m.faces), process=False)
            meshes.append(mm)
            fmats.append(np.full(len(mm.faces), p.mats[kind], np.int32))
        mesh = catalog.concat(meshes)
        lb = _local_bounds(p.model)
        c_local = (lb[0] + lb[1]) / 2
        c_world = p.T[:3, :3] @ c_local + p.T[:3, 3]
        yaw = math.atan2(p.T[1, 0], p.T[0, 0])
        box = OrientedBox(center=vec3(c_world), extent=vec3(lb[1] - lb[0]), yaw_rad=float(yaw))
        cat = p.cat if p.cat != "standing_book" else "book"
        objects.append(SceneObject(
            obj_id=i + 1, label=CATEGORIES[p.cat].label, category=cat, room=p.room, mesh=mesh, box=box,
            parent_id=None if p.parent is None else p.parent + 1, centroid=c_world, T_world_obj=p.T,
            face_material=np.concatenate(fmats), surfaces=tuple(p.model.surfaces),
        ))
    return objects
