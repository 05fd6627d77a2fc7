"""Procedural scenes of the embedded world, deterministic from ``(family, seed)``.

Two families, like the paper's ReplicaCAD split, and a larger apartment setting:

* ``apartment``: 4-6 rooms (living room, kitchen, bedrooms, bathroom, office) joined by doorways, about
  100-130 objects with small items on furniture and inside open containers;
* ``furnished_room``: one room with about 20-30 larger objects;
* ``apartment_large``: the same generator on a bigger footprint (14-18 m x 9-11.5 m) with 7-9 rooms (a
  dining room, up to three bedrooms, a second bathroom) and 150-190 objects: exploration that needs
  more than a few rooms' worth of steps (see ``APARTMENT_SPECS``).

The scene is the ground truth every quality figure is measured against: object ids, natural-language
labels, rooms, world-frame meshes, poses, gravity-aligned oriented boxes, support parents and relations
(``on_top_of``, ``inside``, ``next_to``). World frame: metres, z up, floor at z = 0.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh
from scipy import ndimage

from protocol.messages import OrientedBox, vec3
from protocol.poses import rot_z
from sim import catalog
from sim.catalog import CATEGORIES, Model, Surface
from sim.materials import Material, make_material

FAMILIES: tuple[str, ...] = ("apartment", "furnished_room", "apartment_large")  # append only: the index seeds
PREDICATES: tuple[str, ...] = ("on_top_of", "inside", "next_to")
WALL_T_M = 0.1
DOOR_W_M = 0.9
DOOR_H_M = 2.1
SCENE_FORMAT = "argus-sim-scene"
SCENE_VERSION = 1


@dataclass(frozen=True)
class Room:
    """An axis-aligned rectangular room; ``xy_min``/``xy_max`` bound its free floor (inside the walls)."""

    name: str
    kind: str
    xy_min: np.ndarray
    xy_max: np.ndarray

    def contains(self, x: float, y: float, margin: float = 0.0) -> bool:
        return bool(self.xy_min[0] - margin <= x <= self.xy_max[0] + margin
                    and self.xy_min[1] - margin <= y <= self.xy_max[1] + margin)

    @property
    def area_m2(self) -> float:
        d = self.xy_max - self.xy_min
        return float(d[0] * d[1])


@dataclass(frozen=True)
class Door:
    """A doorway in a wall: centre on the wall line, ``axis`` 0 when the wall runs along x, 1 along y."""

    center_xy: np.ndarray
    axis: int
    width_m: float
    rooms: tuple[str, str]


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One ground-truth object. ``obj_id`` equals its instance id in renders."""

    obj_id: int
    label: str
    category: str
    room: str
    mesh: trimesh.Trimesh
    box: OrientedBox
    parent_id: int | None
    centroid: np.ndarray
    T_world_obj: np.ndarray = field(default_factory=lambda: np.eye(4))
    face_material: np.ndarray | None = None  # (F,) index into Scene.materials
    surfaces: tuple[Surface, ...] = ()  # support surfaces in the object's local frame

    @property
    def yaw_rad(self) -> float:
        return float(math.atan2(self.T_world_obj[1, 0], self.T_world_obj[0, 0]))

    def surfaces_world(self) -> list[tuple[np.ndarray, float, str]]:
        """Each support surface as (4 world xy corners, world z, kind)."""
        out = []
        for s in self.surfaces:
            c = np.array([[s.x0, s.y0, s.z], [s.x1, s.y0, s.z], [s.x1, s.y1, s.z], [s.x0, s.y1, s.z]])
            w = c @ self.T_world_obj[:3, :3].T + self.T_world_obj[:3, 3]
            out.append((w[:, :2], float(w[0, 2]), s.kind))
        return out


@dataclass(eq=False)
class Scene:
    """A generated (or loaded) world: rooms, objects, relations, structure mesh, materials."""

    family: str
    seed: int
    rooms: list[Room]
    objects: list[SceneObject]
    relations: list[tuple[int, str, int]]
    bounds_min: np.ndarray
    bounds_max: np.ndarray
    structure: trimesh.Trimesh
    structure_face_material: np.ndarray
    materials: list[Material]
    doors: list[Door] = field(default_factory=list)
    wall_height_m: float = 2.6

    def __post_init__(self) -> None:
        self._by_id = {o.obj_id: o for o in self.objects}

    def object_by_id(self, obj_id: int) -> SceneObject:
        """The object with ``obj_id``; ``KeyError`` if none."""
        return self._by_id[int(obj_id)]

    def room_at(self, x: float, y: float) -> Room | None:
        """The room whose floor contains (x, y) (doorways count for the nearest room), or None."""
        for r in self.rooms:
            if r.contains(x, y):
                return r
        for r in self.rooms:
            if r.contains(x, y, margin=WALL_T_M):
                return r
        return None

    def labels(self) -> dict[int, str]:
        """obj_id -> label (what an ORACLE segmenter reports)."""
        return {o.obj_id: o.label for o in self.objects}

    def summary(self) -> dict[str, Any]:
        per_room: dict[str, int] = {}
        for o in self.objects:
            per_room[o.room] = per_room.get(o.room, 0) + 1
        return {
            "family": self.family,
            "seed": self.seed,
            "rooms": [r.name for r in self.rooms],
            "n_objects": len(self.objects),
            "n_categories": len({o.category for o in self.objects}),
            "n_relations": len(self.relations),
            "objects_per_room": per_room,
        }

    # -- serialisation -------------------------------------------------------------------------
    def to_json(self, include_meshes: bool = True) -> dict[str, Any]:
        """A JSON-able dict of everything; meshes inline (base64) unless ``include_meshes`` is False."""

        def mesh_dict(m: trimesh.Trimesh, fm: np.ndarray | None) -> dict[str, str]:
            d = {
                "vertices": _b64(np.asarray(m.vertices, np.float64)),
                "faces": _b64(np.asarray(m.faces, np.int32)),
            }
            if fm is not None:
                d["face_material"] = _b64(np.asarray(fm, np.int32))
            return d

        objs = []
        for o in self.objects:
            d: dict[str, Any] = {
                "obj_id": o.obj_id,
                "label": o.label,
                "category": o.category,
                "room": o.room,
                "parent_id": o.parent_id,
                "centroid": [float(v) for v in o.centroid],
                "box": o.box.model_dump(mode="json"),
                "T_world_obj": np.asarray(o.T_world_obj).tolist(),
                "surfaces": [vars(s) for s in o.surfaces],
            }
            if include_meshes:
                d["mesh"] = mesh_dict(o.mesh, o.face_material)
            objs.append(d)
        out: dict[str, Any] = {
            "format": SCENE_FORMAT,
            "version": SCENE_VERSION,
            "family": self.family,
            "seed": self.seed,
            "wall_height_m": self.wall_height_m,
            "bounds_min": [float(v) for v in self.bounds_min],
            "bounds_max": [float(v) for v in self.bounds_max],
            "rooms": [{"name": r.name, "kind": r.kind, "xy_min": r.xy_min.tolist(), "xy_max": r.xy_max.tolist()}
                      for r in self.rooms],
            "doors": [{"center_xy": d.center_xy.tolist(), "axis": d.axis, "width_m": d.width_m,
                       "rooms": list(d.rooms)} for d in self.doors],
            "materials": [m.to_dict() for m in self.materials],
            "objects": objs,
            "relations": [[int(a), p, int(b)] for a, p, b in self.relations],
        }
        if include_meshes:
            out["structure"] = mesh_dict(self.structure, self.structure_face_material)
        return out

    @classmethod
    def from_json(
        cls,
        data: dict[str, Any],
        meshes: Mapping[int, tuple[trimesh.Trimesh, np.ndarray | None]] | None = None,
        structure: tuple[trimesh.Trimesh, np.ndarray | None] | None = None,
    ) -> Scene:
        """Rebuild a scene from :meth:`to_json` output; meshes come inline or from ``meshes``/``structure``
        (obj_id -> (mesh, face_material)), e.g. as read back from glTF."""
        if data.get("format") != SCENE_FORMAT:
            raise ValueError(f"not an Argus sim scene (format {data.get('format')!r})")
        if int(data.get("version", -1)) > SCENE_VERSION:
            raise ValueError(f"scene version {data.get('version')} is newer than supported {SCENE_VERSION}")
        materials = [Material.from_dict(m) for m in data["materials"]]
        objects = []
        for d in data["objects"]:
            oid = int(d["obj_id"])
            if meshes is not None and oid in meshes:
                mesh, fm = meshes[oid]
            elif "mesh" in d:
                mesh, fm = _mesh_from(d["mesh"])
            else:
                raise ValueError(f"object {oid} ({d.get('label')}) has no mesh")
            if fm is None or len(fm) != len(mesh.faces):
                fm = np.zeros(len(mesh.faces), np.int32)
            objects.append(SceneObject(
                obj_id=oid,
                label=str(d["label"]),
                category=str(d.get("category", str(d["label"]).replace(" ", "_"))),
                room=str(d.get("room", "")),
                mesh=mesh,
                box=OrientedBox.model_validate(d["box"]),
                parent_id=None if d.get("parent_id") is None else int(d["parent_id"]),
                centroid=np.asarray(d["centroid"], np.float64),
                T_world_obj=np.asarray(d.get("T_world_obj", np.eye(4).tolist()), np.float64),
                face_material=np.asarray(fm, np.int32),
                surfaces=tuple(Surface(**s) for s in d.get("surfaces", [])),
            ))
        if structure is not None:
            smesh, sfm = structure
        elif "structure" in data:
            smesh, sfm = _mesh_from(data["structure"])
        else:
            raise ValueError("scene has no structure mesh")
        if sfm is None or len(sfm) != len(smesh.faces):
            sfm = np.zeros(len(smesh.faces), np.int32)
        return cls(
            family=str(data["family"]),
            seed=int(data["seed"]),
            rooms=[Room(r["name"], r["kind"], np.asarray(r["xy_min"], float), np.asarray(r["xy_max"], float))
                   for r in data["rooms"]],
            objects=objects,
            relations=[(int(a), str(p), int(b)) for a, p, b in data["relations"]],
            bounds_min=np.asarray(data["bounds_min"], float),
            bounds_max=np.asarray(data["bounds_max"], float),
            structure=smesh,
            structure_face_material=np.asarray(sfm, np.int32),
            materials=materials,
            doors=[Door(np.asarray(d["center_xy"], float), int(d["axis"]), float(d["width_m"]),
                        (str(d["rooms"][0]), str(d["rooms"][1]))) for d in data.get("doors", [])],
            wall_height_m=float(data.get("wall_height_m", 2.6)),
        )


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def _mesh_from(d: dict[str, str]) -> tuple[trimesh.Trimesh, np.ndarray | None]:
    v = np.frombuffer(base64.b64decode(d["vertices"]), np.float64).reshape(-1, 3)
    f = np.frombuffer(base64.b64decode(d["faces"]), np.int32).reshape(-1, 3)
    fm = np.frombuffer(base64.b64decode(d["face_material"]), np.int32) if "face_material" in d else None
    return trimesh.Trimesh(vertices=v.copy(), faces=f.copy(), process=False), fm


# =================================================================================================
# Generation.

_ROOM_ORDER = {
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


def _split_layout(rng: np.random.Generator, n_rooms: int, spec: ApartmentSpec = APARTMENT_SPECS["apartment"]
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


class _Builder:
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


def _structure(b: _Builder, rects: list[np.ndarray], rooms: list[Room], doors: list[Door], size: tuple[float, float],
               H: float) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Floor, walls with door openings, ceiling, windows; per-face material indices."""
    W, D = size
    t = WALL_T_M
    parts: list[tuple[trimesh.Trimesh, int | str]] = []
    room_mats: dict[str, tuple[int, int]] = {}
    for room, r in zip(rooms, rects, strict=True):
        floor_kind = "tile_floor" if room.kind in ("kitchen", "bathroom") else (
            "carpet" if room.kind == "bedroom" and b.rng.random() < 0.35 else "wood_floor")
        wall_kind = "tile_wall" if room.kind == "bathroom" else "paint"
        room_mats[room.name] = (b.material(floor_kind), b.material(wall_kind))
        parts.append((catalog.box(r[2] - r[0], r[3] - r[1], 0.05, (r[0] + r[2]) / 2, (r[1] + r[3]) / 2, -0.05),
                      room_mats[room.name][0]))
    ceiling = b.material("ceiling")
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
    win = b.material("window")
    frame = b.material("white")
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
        ax, c, lo, hi = sides[int(b.rng.integers(len(sides)))]
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
    neutral = b.material("paint")
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


def _place_furniture(b: _Builder, room: Room, doors: list[Door], plan: list[tuple[str, str, float]],
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


def _try_place_item(b: _Builder, parent_idx: int, cat: str, occupied: dict[tuple[int, int], list]) -> bool:
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


def _fill_items(b: _Builder, target: int, large_only: bool) -> None:
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


def _finalise(b: _Builder, family: str, seed: int, rooms: list[Room], doors: list[Door],
              structure: tuple[trimesh.Trimesh, np.ndarray], wall_h: float) -> Scene:
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
    relations = compute_relations(objects, [p.surface_kind for p in b.placed])
    smesh = structure[0]
    all_v = np.vstack([smesh.vertices] + [o.mesh.vertices for o in objects])
    return Scene(family=family, seed=seed, rooms=rooms, objects=objects, relations=relations,
                 bounds_min=all_v.min(0), bounds_max=all_v.max(0), structure=smesh,
                 structure_face_material=structure[1], materials=b.materials, doors=doors, wall_height_m=wall_h)


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


def generate_scene(family: str, seed: int) -> Scene:
    """Generate the scene ``(family, seed)``; the same arguments always give the same scene."""
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family {family!r}; expected one of {FAMILIES}")
    seed = int(seed)
    fam_code = FAMILIES.index(family)
    rng = np.random.default_rng([seed & 0xFFFFFFFF, fam_code, 0xA5605])
    b = _Builder(rng)
    H = round(float(rng.uniform(2.5, 2.8)), 2)
    if family in APARTMENT_SPECS:
        spec = APARTMENT_SPECS[family]
        n_rooms = int(rng.choice(list(spec.rooms), p=list(spec.rooms_p)))
        rects, raw_doors, size = _split_layout(rng, n_rooms, spec)
        areas = [(r[2] - r[0]) * (r[3] - r[1]) for r in rects]
        order = np.argsort(areas)[::-1]
        kinds = [""] * n_rooms
        for rank, idx in enumerate(order):
            kinds[int(idx)] = _ROOM_ORDER[n_rooms][rank]
        target = int(rng.integers(spec.objects[0], spec.objects[1] + 1))
    else:
        W, D = float(rng.uniform(4.5, 6.5)), float(rng.uniform(4.0, 5.5))
        rects, raw_doors, size = [np.array([0.0, 0.0, W, D])], [], (W, D)
        kinds = [str(rng.choice(["living_room", "bedroom", "office", "dining_room", "kitchen"]))]
        target = int(rng.integers(20, 31))
    names: list[str] = []
    counts: dict[str, int] = {}
    for k in kinds:
        counts[k] = counts.get(k, 0) + 1
    seen: dict[str, int] = {}
    for k in kinds:
        seen[k] = seen.get(k, 0) + 1
        names.append(f"{k}_{seen[k]}" if counts[k] > 1 else k)
    t = WALL_T_M / 2
    rooms = [Room(n, k, np.array([r[0] + t, r[1] + t]), np.array([r[2] - t, r[3] - t]))
             for n, k, r in zip(names, kinds, rects, strict=True)]
    doors = []
    for x, y, ax in raw_doors:
        off = np.array([0.0, 0.3]) if ax == 0 else np.array([0.3, 0.0])
        ra = next(r.name for r in rooms if r.contains(*(np.array([x, y]) - off)))
        rb = next(r.name for r in rooms if r.contains(*(np.array([x, y]) + off)))
        doors.append(Door(np.array([x, y]), ax, DOOR_W_M, (ra, rb)))
    structure = _structure(b, rects, rooms, doors, size, H)
    for room in rooms:
        plan = list(_PLANS[room.kind])
        if family == "furnished_room":
            plan += [("potted_plant", "corner", 0.7), ("floor_lamp", "corner", 0.6), ("bookshelf", "wall", 0.6),
                     ("armchair", "wall", 0.5), ("side_table", "wall", 0.6), ("dresser", "wall", 0.5),
                     ("trash_can", "corner", 0.5), ("chair", "wall", 0.4), ("potted_plant", "corner", 0.5)]
        _place_furniture(b, room, doors, plan, H)
    _fill_items(b, target, large_only=family == "furnished_room")
    return _finalise(b, family, seed, rooms, doors, structure, H)
