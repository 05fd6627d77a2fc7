"""Scenes that change during an episode: objects moved (within a room or to another), removed, added.

An :class:`Edit` happens at a time ``t_s``; a :class:`ChangingScene` is a generated scene plus a time-ordered list of
edits, and answers what the world is at any time: :meth:`ChangingScene.scene_at` is a plain :class:`sim.world.Scene`
(the ground truth at that time: which objects exist and where, their relations), :meth:`ChangingScene.render` draws
it (with people, :mod:`sim.people`, when given). With no edits the scene at every time is the generated scene itself,
object for object, and renders bit for bit as before.

Edits come scripted (:func:`move_edit`, :func:`remove_edit`, :func:`add_edit`, or a list of dicts through
:func:`edits_from_spec`) or drawn at random (:func:`random_edits`, deterministic from a seed). Random edits touch only
objects that support nothing: floor-standing objects people push around (chairs, plants, lamps, bins, baskets) move
to free floor near a wall, small items on tables and shelves move to the top of other furniture; additions are things
left behind (a backpack or a box on the floor, a mug or a book on a table). A moved object keeps its id; an added
one gets the next free id. Example::

    scene = generate_scene("apartment", 0)
    world = ChangingScene(scene, random_edits(scene, n=6, duration_s=60.0, seed=0))
    world.scene_at(30.0).objects                      # the ground truth at t = 30 s
    world.render(K, T_world_cam, 30.0, people=people)  # RGB, depth, instance ids at t = 30 s
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import trimesh

from protocol.messages import Intrinsics, OrientedBox, vec3
from protocol.poses import rot_z
from sim.materials import Material
from sim.relations import compute_relations
from sim.world import Scene, SceneObject

EDIT_KINDS: tuple[str, ...] = ("move", "remove", "add")
MOVABLE_FLOOR: frozenset[str] = frozenset({
    "chair", "dining_chair", "bar_stool", "office_chair", "potted_plant", "floor_lamp", "trash_can",
    "laundry_basket", "armchair", "side_table"})
"""Floor-standing categories a person may push elsewhere (when nothing stands on them)."""
ADD_FLOOR: tuple[str, ...] = ("backpack", "storage_box", "laundry_basket", "trash_can", "basket")
ADD_SURFACE: tuple[str, ...] = ("mug", "book", "vase", "small_plant", "storage_box", "laptop")
MIN_MOVE_M = 1.0  # a move shorter than twice the scoring radius would not tell moved from unmoved


@dataclass(frozen=True, eq=False)
class Edit:
    """One change at ``t_s`` seconds. ``kind``: ``move`` (``obj`` is the object at its new place, same id),
    ``remove`` (``obj`` None) or ``add`` (``obj`` is the new object; its face materials index ``materials``, the
    new object's own). ``note`` says what happened in words."""

    t_s: float
    kind: str
    obj_id: int
    obj: SceneObject | None = None
    materials: tuple[Material, ...] = ()
    note: str = ""

    def __post_init__(self) -> None:
        if self.kind not in EDIT_KINDS:
            raise ValueError(f"unknown edit kind {self.kind!r}; expected one of {EDIT_KINDS}")
        if not math.isfinite(self.t_s) or self.t_s < 0:
            raise ValueError("an edit's time must be finite and >= 0")
        if (self.obj is None) != (self.kind == "remove"):
            raise ValueError(f"a {self.kind} edit {'needs' if self.kind != 'remove' else 'takes no'} object")
        if self.obj is not None and self.obj.obj_id != self.obj_id:
            raise ValueError("an edit's object must carry the edit's obj_id")


def placed(obj: SceneObject, T_world_obj: np.ndarray, room: str | None = None,
           parent_id: int | None = None) -> SceneObject:
    """``obj`` moved rigidly so that its pose is ``T_world_obj`` (mesh, box, centroid follow; same id)."""
    T_new = np.asarray(T_world_obj, np.float64)
    D = T_new @ np.linalg.inv(np.asarray(obj.T_world_obj, np.float64))
    v = np.asarray(obj.mesh.vertices, np.float64) @ D[:3, :3].T + D[:3, 3]
    mesh = trimesh.Trimesh(vertices=v, faces=np.asarray(obj.mesh.faces).copy(), process=False)
    dyaw = math.atan2(D[1, 0], D[0, 0])
    c = D[:3, :3] @ np.asarray(obj.box.center, np.float64) + D[:3, 3]
    box = OrientedBox(center=vec3(c), extent=obj.box.extent, yaw_rad=float(_wrap(obj.box.yaw_rad + dyaw)))
    return replace(obj, mesh=mesh, box=box, centroid=D[:3, :3] @ np.asarray(obj.centroid, np.float64) + D[:3, 3],
                   T_world_obj=T_new, room=obj.room if room is None else room, parent_id=parent_id)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_z(yaw)
    T[:3, 3] = (x, y, z)
    return T


def _local_bounds(obj: SceneObject) -> np.ndarray:
    """(2, 3) bounds of ``obj``'s mesh in its own frame (catalog models stand on z = 0)."""
    T = np.asarray(obj.T_world_obj, np.float64)
    v = (np.asarray(obj.mesh.vertices, np.float64) - T[:3, 3]) @ T[:3, :3]
    return np.stack([v.min(0), v.max(0)])


def _footprint(lb: np.ndarray, T: np.ndarray) -> tuple[float, float, float, float]:
    c = np.array([[lb[0, 0], lb[0, 1]], [lb[1, 0], lb[0, 1]], [lb[1, 0], lb[1, 1]], [lb[0, 0], lb[1, 1]]])
    w = c @ T[:2, :2].T + T[:2, 3]
    return float(w[:, 0].min()), float(w[:, 1].min()), float(w[:, 0].max()), float(w[:, 1].max())


def _overlap(a: tuple[float, ...], b: tuple[float, ...], pad: float) -> bool:
    return not (a[2] + pad <= b[0] or b[2] + pad <= a[0] or a[3] + pad <= b[1] or b[3] + pad <= a[1])


# --- the changing world --------------------------------------------------------------------------------------
def apply_edit(scene: Scene, edit: Edit, material_offset: int = 0) -> Scene:
    """The scene after ``edit`` (a new :class:`Scene`; ``scene`` is left as it is). An added object's face
    materials are shifted by ``material_offset`` (where its materials start in ``scene.materials``). Support
    relations of the edited object follow its new parent; ``next_to`` is recomputed."""
    objs = [o for o in scene.objects if o.obj_id != edit.obj_id]
    ids = {o.obj_id for o in scene.objects}
    if edit.kind in ("move", "remove") and edit.obj_id not in ids:
        raise ValueError(f"edit at {edit.t_s:.1f} s: object {edit.obj_id} is not in the scene")
    if edit.kind == "add" and edit.obj_id in ids:
        raise ValueError(f"edit at {edit.t_s:.1f} s: object id {edit.obj_id} is taken")
    if edit.kind != "remove" and any(o.parent_id == edit.obj_id for o in objs):
        raise ValueError(f"object {edit.obj_id} supports other objects: move or remove them first")
    if edit.kind == "remove" and any(o.parent_id == edit.obj_id for o in objs):
        raise ValueError(f"object {edit.obj_id} supports other objects: remove them first")
    if edit.obj is not None:
        new = edit.obj
        if edit.kind == "add" and new.face_material is not None and material_offset:
            new = replace(new, face_material=np.asarray(new.face_material, np.int32) + material_offset)
        objs.append(new)
        objs.sort(key=lambda o: o.obj_id)
    inside = {(a, b) for a, p, b in scene.relations if p == "inside"}
    kinds: list[str | None] = [None if o.parent_id is None else
                               "in" if (o.obj_id, o.parent_id) in inside else "on" for o in objs]
    relations = compute_relations(objs, kinds)
    return Scene(family=scene.family, seed=scene.seed, rooms=scene.rooms, objects=objs, relations=relations,
                 bounds_min=scene.bounds_min, bounds_max=scene.bounds_max, structure=scene.structure,
                 structure_face_material=scene.structure_face_material, materials=scene.materials,
                 doors=scene.doors, wall_height_m=scene.wall_height_m)


class ChangingScene:
    """A scene and its edits over time: the ground truth at any time and renders of it.

    ``states[k]`` is the scene after the first ``k`` edits (``states[0]`` is ``scene`` itself); the materials of
    added objects are appended to every state's material list, which leaves the generated objects' renders as
    they were."""

    def __init__(self, scene: Scene, edits: Sequence[Edit] = (), renderer_cache: int = 2) -> None:
        self.base = scene
        self.edits: list[Edit] = sorted(edits, key=lambda e: e.t_s)
        extra = [m for e in self.edits for m in e.materials]
        first = scene if not extra else replace_materials(scene, list(scene.materials) + extra)
        self.states: list[Scene] = [first]
        offset = len(scene.materials)
        for e in self.edits:
            self.states.append(apply_edit(self.states[-1], e, offset))
            offset += len(e.materials)
        self.times_s = np.array([e.t_s for e in self.edits], float)
        self._renderers: OrderedDict[int, Any] = OrderedDict()
        self._cap = max(1, int(renderer_cache))

    def state_index(self, t_s: float) -> int:
        """How many edits have happened at ``t_s`` (an edit at exactly ``t_s`` has)."""
        return int(np.searchsorted(self.times_s, t_s, side="right"))

    def scene_at(self, t_s: float) -> Scene:
        """The world at ``t_s``: every object that exists then, where it is then."""
        return self.states[self.state_index(t_s)]

    def objects_at(self, t_s: float) -> list[SceneObject]:
        return self.scene_at(t_s).objects

    def renderer_at(self, t_s: float, backend: str = "embree") -> Any:
        """A :class:`sim.render.Renderer` of the world at ``t_s`` (the last few are kept)."""
        k = self.state_index(t_s)
        r = self._renderers.get(k)
        if r is None:
            from sim.render import Renderer

            r = self._renderers[k] = Renderer(self.states[k], backend=backend)
            while len(self._renderers) > self._cap:
                self._renderers.popitem(last=False)
        else:
            self._renderers.move_to_end(k)
        return r

    def render(self, intrinsics: Intrinsics, T_world_cam: np.ndarray, t_s: float, people: Any = None) -> Any:
        """RGB, depth and instance ids at ``t_s`` from ``T_world_cam``, with ``people`` (:class:`sim.people.People`)
        walking through when given."""
        overlay = people.layer(t_s) if people is not None else None
        return self.renderer_at(t_s).render(intrinsics, T_world_cam, overlay=overlay)

    def labels_at(self, t_s: float, people: Any = None) -> dict[int, str]:
        """Instance id -> label at ``t_s`` (what the ORACLE semantic camera reports), people included."""
        out = self.scene_at(t_s).labels()
        if people is not None:
            out.update(people.labels())
        return out

    def next_id(self) -> int:
        """The smallest id no object ever had in this episode."""
        return 1 + max([o.obj_id for s in self.states for o in s.objects], default=0)


def replace_materials(scene: Scene, materials: list[Material]) -> Scene:
    """``scene`` with another material list (the objects and everything else shared)."""
    return Scene(family=scene.family, seed=scene.seed, rooms=scene.rooms, objects=scene.objects,
                 relations=scene.relations, bounds_min=scene.bounds_min, bounds_max=scene.bounds_max,
                 structure=scene.structure, structure_face_material=scene.structure_face_material,
                 materials=materials, doors=scene.doors, wall_height_m=scene.wall_height_m)


# --- scripted edits ------------------------------------------------------------------------------------------
def move_edit(scene: Scene, obj_id: int, t_s: float, xy: Sequence[float], yaw_rad: float | None = None,
              z: float | None = None, parent_id: int | None = None) -> Edit:
    """Move object ``obj_id`` of ``scene`` (the world just before ``t_s``) so that its pose's origin (the middle of
    its footprint, on its support) is at ``xy`` (height ``z``, default: as before), turned to ``yaw_rad`` (default:
    as before), standing on ``parent_id`` (default: the floor)."""
    obj = scene.object_by_id(obj_id)
    T = np.asarray(obj.T_world_obj, np.float64)
    yaw = obj.yaw_rad if yaw_rad is None else float(yaw_rad)
    zz = float(T[2, 3]) if z is None else float(z)
    room = scene.room_at(float(xy[0]), float(xy[1]))
    new = placed(obj, _pose(float(xy[0]), float(xy[1]), zz, yaw), room.name if room else obj.room, parent_id)
    where = "within " + obj.room if new.room == obj.room else f"{obj.room} -> {new.room}"
    return Edit(t_s=float(t_s), kind="move", obj_id=obj.obj_id, obj=new, note=f"{obj.label} moved {where}")


def remove_edit(scene: Scene, obj_id: int, t_s: float) -> Edit:
    """Take object ``obj_id`` away at ``t_s``."""
    obj = scene.object_by_id(obj_id)
    return Edit(t_s=float(t_s), kind="remove", obj_id=obj.obj_id, note=f"{obj.label} removed from {obj.room}")


def new_object(category: str, obj_id: int, seed: int) -> tuple[SceneObject, list[Material]]:
    """A catalog object of ``category`` (e.g. ``backpack``) with id ``obj_id`` at the world origin, and the
    materials its faces index (from 0). Built by the generator's own code (:mod:`sim.furnish`)."""
    from sim.catalog import CATEGORIES
    from sim.furnish import Builder, _Placed, scene_objects

    if category not in CATEGORIES:
        raise ValueError(f"unknown object category {category!r}")
    b = Builder(np.random.default_rng([int(seed) & 0xFFFFFFFF, int(obj_id), 0xADD]))
    model = CATEGORIES[category].build(b.rng)
    b.placed.append(_Placed(category, model, np.eye(4), "", None, None, None, math.inf, b.mats_for(model)))
    obj = scene_objects(b)[0]
    return replace(obj, obj_id=int(obj_id)), list(b.materials)


def add_edit(scene: Scene, category: str, t_s: float, xy: Sequence[float], obj_id: int, yaw_rad: float = 0.0,
             z: float = 0.0, parent_id: int | None = None, seed: int = 0) -> Edit:
    """Put a new ``category`` object with id ``obj_id`` at ``xy`` (its footprint's middle; bottom at ``z``) at
    ``t_s``, standing on ``parent_id`` (default: the floor)."""
    obj, mats = new_object(category, obj_id, seed)
    room = scene.room_at(float(xy[0]), float(xy[1]))
    new = placed(obj, _pose(float(xy[0]), float(xy[1]), float(z), float(yaw_rad)), room.name if room else "",
                 parent_id)
    return Edit(t_s=float(t_s), kind="add", obj_id=int(obj_id), obj=new, materials=tuple(mats),
                note=f"{new.label} added to {new.room or 'nowhere'}")


def edits_from_spec(scene: Scene, spec: Iterable[Mapping[str, Any]], seed: int = 0) -> list[Edit]:
    """Scripted edits from plain data (a TOML or JSON list), applied in time order, each to the world as the
    earlier ones left it: ``{t_s, kind = "move", obj_id, to = [x, y], yaw_deg?, z?, parent_id?}``,
    ``{t_s, kind = "remove", obj_id}``, ``{t_s, kind = "add", category, to = [x, y], yaw_deg?, z?, parent_id?}``."""
    edits: list[Edit] = []
    world = ChangingScene(scene)
    for d in sorted(spec, key=lambda d: float(d["t_s"])):
        state = world.states[-1]
        kind, t = str(d["kind"]), float(d["t_s"])
        yaw = None if d.get("yaw_deg") is None else math.radians(float(d["yaw_deg"]))
        if kind == "move":
            e = move_edit(state, int(d["obj_id"]), t, d["to"], yaw, d.get("z"), d.get("parent_id"))
        elif kind == "remove":
            e = remove_edit(state, int(d["obj_id"]), t)
        elif kind == "add":
            e = add_edit(state, str(d["category"]), t, d["to"], world.next_id(), yaw or 0.0, float(d.get("z", 0.0)),
                         d.get("parent_id"), seed)
        else:
            raise ValueError(f"unknown edit kind {kind!r}; expected one of {EDIT_KINDS}")
        edits.append(e)
        world = ChangingScene(scene, edits)
    return edits


# --- random edits --------------------------------------------------------------------------------------------
def _children(scene: Scene) -> set[int]:
    return {o.parent_id for o in scene.objects if o.parent_id is not None}


def movable(scene: Scene, min_size_m: float = 0.12) -> list[SceneObject]:
    """Objects a random edit may move or remove: nothing stands on them; floor objects of :data:`MOVABLE_FLOOR`
    and items on top of furniture at least ``min_size_m`` across."""
    parents = _children(scene)
    out = []
    for o in scene.objects:
        if o.obj_id in parents:
            continue
        if o.parent_id is None:
            if o.category in MOVABLE_FLOOR:
                out.append(o)
        elif max(o.box.extent[:2]) >= min_size_m:
            out.append(o)
    return out


def floor_spot(scene: Scene, nav: Any, lb: np.ndarray, room: Any, rng: np.random.Generator,
               avoid_xy: Sequence[Sequence[float]] = (), min_dist_m: float = 0.0, door_clear_m: float = 1.0,
               tries: int = 200) -> tuple[float, float, float] | None:
    """A free floor pose (x, y, yaw) in ``room`` for a model with local bounds ``lb``: its footprint on free floor
    of ``nav`` (the world as it is), clear of doorways, near a wall (so that it blocks no passage), at least
    ``min_dist_m`` from each of ``avoid_xy``."""
    cells = nav.room_cells(room)
    if len(cells) == 0:
        return None
    wall_d = np.minimum.reduce([cells[:, 0] - room.xy_min[0], room.xy_max[0] - cells[:, 0],
                                cells[:, 1] - room.xy_min[1], room.xy_max[1] - cells[:, 1]])
    order = np.argsort(wall_d + rng.uniform(0.0, 0.6, len(cells)))
    doors = np.array([d.center_xy for d in scene.doors]).reshape(-1, 2)
    for k in order[:tries]:
        x, y = (float(v) for v in cells[k])
        if len(doors) and float(np.min(np.hypot(doors[:, 0] - x, doors[:, 1] - y))) < door_clear_m:
            continue
        if any(math.hypot(x - a[0], y - a[1]) < min_dist_m for a in avoid_xy):
            continue
        yaw = float(rng.uniform(-math.pi, math.pi))
        fp = _footprint(lb, _pose(x, y, 0.0, yaw))
        j0, i0 = nav.cell_of(fp[0] - 0.05, fp[1] - 0.05)
        j1, i1 = nav.cell_of(fp[2] + 0.05, fp[3] + 0.05)
        if j0 < 0 or i0 < 0 or j1 >= nav.shape[0] or i1 >= nav.shape[1]:
            continue
        if nav.floor[j0:j1 + 1, i0:i1 + 1].all():
            return x, y, yaw
    return None


def surface_spot(scene: Scene, lb: np.ndarray, room: str, rng: np.random.Generator, exclude: set[int],
                 avoid_xy: Sequence[Sequence[float]] = (), min_dist_m: float = 0.0,
                 tries: int = 60, max_z_m: float = 1.3) -> tuple[np.ndarray, int] | None:
    """A pose on top of a piece of furniture in ``room`` (not one of ``exclude``) for a model with local bounds
    ``lb``: on an ``on`` surface at most ``max_z_m`` high (where people put things, and cameras see them) with
    headroom, clear of the items already there; and the furniture's id."""
    parents = [o for o in scene.objects if o.room == room and o.obj_id not in exclude
               and any(s.kind == "on" for s in o.surfaces)]
    if not parents:
        return None
    h = float(lb[1, 2] - lb[0, 2])
    for _ in range(tries):
        p = parents[int(rng.integers(len(parents)))]
        ons = [s for s in p.surfaces if s.kind == "on" and s.clear_m > h + 0.01]
        if not ons:
            continue
        s = ons[int(rng.integers(len(ons)))]
        yaw_l = float(rng.choice([0.0, math.pi / 2, math.pi, -math.pi / 2]) + rng.uniform(-0.3, 0.3))
        fx = _footprint(lb, _pose(0.0, 0.0, 0.0, yaw_l))
        xr = (s.x0 - fx[0], s.x1 - fx[2])
        yr = (s.y0 - fx[1], s.y1 - fx[3])
        if xr[1] < xr[0] or yr[1] < yr[0]:
            continue
        x, y = float(rng.uniform(*xr)), float(rng.uniform(*yr))
        T = np.asarray(p.T_world_obj, np.float64) @ _pose(x, y, s.z - float(lb[0, 2]), yaw_l)
        if T[2, 3] > max_z_m or any(math.hypot(T[0, 3] - a[0], T[1, 3] - a[1]) < min_dist_m for a in avoid_xy):
            continue
        fp = _footprint(lb, T)
        if any(_overlap(fp, _footprint(_local_bounds(o), np.asarray(o.T_world_obj)), 0.02)
               for o in scene.objects if o.parent_id == p.obj_id and o.obj_id not in exclude):
            continue
        return T, p.obj_id
    return None


def random_edits(scene: Scene, n: int, duration_s: float, seed: int, kinds: Sequence[str] = EDIT_KINDS,
                 rooms: Sequence[str] | None = None, window: tuple[float, float] = (0.2, 0.75),
                 cross_room: float = 0.5, focus: Sequence[str] | None = None) -> list[Edit]:
    """``n`` edits spread over ``window`` (fractions of ``duration_s``), kinds in turn from ``kinds`` (shuffled),
    each in a random room (of ``rooms`` if given; every other edit, the first included, in one of ``focus`` if
    given: e.g. the rooms fixed cameras watch); a move goes to another room with probability ``cross_room`` (if
    there is one) and at least :data:`MIN_MOVE_M` away. No object is edited twice. Deterministic from ``seed``; an
    edit with no place to go is skipped, so fewer than ``n`` may come back."""
    for name in kinds:
        if name not in EDIT_KINDS:
            raise ValueError(f"unknown edit kind {name!r}; expected one of {EDIT_KINDS}")
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0xED17])
    order = [kinds[i % len(kinds)] for i in range(n)] if kinds else []
    rng.shuffle(order)
    lo, hi = window
    times = [duration_s * (lo + (hi - lo) * (k + float(rng.uniform(0.2, 0.8))) / max(n, 1)) for k in range(n)]
    allowed = [r for r in scene.rooms if rooms is None or r.name in rooms]
    if not allowed:
        raise ValueError(f"no such rooms in the scene: {rooms}")
    edits: list[Edit] = []
    touched: set[int] = set()
    world = ChangingScene(scene)
    focused = [r for r in allowed if focus is not None and r.name in focus]
    for i, (t, kind) in enumerate(zip(times, order, strict=True)):
        state = world.states[-1]
        where = focused if focused and i % 2 == 0 else allowed
        e = _random_edit(state, world, kind, t, where, rng, touched, cross_room, seed)
        if e is None:
            continue
        edits.append(e)
        touched.add(e.obj_id)
        if e.obj is not None and e.obj.parent_id is not None:
            touched.add(e.obj.parent_id)  # never removed or moved from under the new item
        world = ChangingScene(scene, edits)
    return edits


def _random_edit(state: Scene, world: ChangingScene, kind: str, t: float, rooms: list[Any],
                 rng: np.random.Generator, touched: set[int], cross_room: float, seed: int,
                 attempts: int = 6) -> Edit | None:
    names = {r.name for r in rooms}
    by_name = {r.name: r for r in state.rooms}
    navs: dict[int, Any] = {}  # the navigation map of this state, built once if a floor spot is looked for
    for _ in range(attempts):
        if kind == "add":
            room = rooms[int(rng.integers(len(rooms)))]
            on_floor = bool(rng.random() < 0.5)
            pool = ADD_FLOOR if on_floor else ADD_SURFACE
            obj_id = world.next_id()
            obj, mats = new_object(pool[int(rng.integers(len(pool)))], obj_id, seed)
            lb = _local_bounds(obj)
            spot = _spot(state, navs, obj, lb, room, on_floor, rng, touched, (), 0.0)
            if spot is None:
                continue
            T, parent = spot
            new = placed(obj, T, room.name, parent)
            return Edit(t_s=t, kind="add", obj_id=obj_id, obj=new, materials=tuple(mats),
                        note=f"{new.label} added to {room.name}" + (" (on the floor)" if parent is None else ""))
        cands = [o for o in movable(state) if o.room in names and o.obj_id not in touched]
        if not cands:
            return None
        # half the picks among floor-standing objects (fewer, but bigger: what people push around)
        floor = [o for o in cands if o.parent_id is None]
        pool_o = floor if floor and rng.random() < 0.5 else cands
        obj = pool_o[int(rng.integers(len(pool_o)))]
        if kind == "remove":
            return Edit(t_s=t, kind="remove", obj_id=obj.obj_id, note=f"{obj.label} removed from {obj.room}")
        others = [r for r in state.rooms if r.name != obj.room and (r.name in names or len(names) == 1)]
        to = others[int(rng.integers(len(others)))] if others and rng.random() < cross_room else by_name[obj.room]
        lb = _local_bounds(obj)
        spot = _spot(state, navs, obj, lb, to, obj.parent_id is None, rng, touched | {obj.obj_id, obj.parent_id or 0},
                     [tuple(float(v) for v in obj.T_world_obj[:2, 3])], MIN_MOVE_M)
        if spot is None:
            continue
        T, parent = spot
        new = placed(obj, T, to.name, parent)
        where = f"within {obj.room}" if to.name == obj.room else f"{obj.room} -> {to.name}"
        return Edit(t_s=t, kind="move", obj_id=obj.obj_id, obj=new, note=f"{obj.label} moved {where}")
    return None


def _spot(state: Scene, navs: dict[int, Any], obj: SceneObject, lb: np.ndarray, room: Any, on_floor: bool,
          rng: np.random.Generator, exclude: set[int], avoid: Sequence[Sequence[float]],
          min_dist: float) -> tuple[np.ndarray, int | None] | None:
    if on_floor:
        if 0 not in navs:
            from sim.nav import NavMap

            navs[0] = NavMap(state)
        s = floor_spot(state, navs[0], lb, room, rng, avoid, min_dist)
        if s is None:
            return None
        return _pose(s[0], s[1], 0.0, s[2]), None
    found = surface_spot(state, lb, room.name, rng, exclude, avoid, min_dist)
    if found is None:
        return None
    return found[0], found[1]
