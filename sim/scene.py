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

import numpy as np

from sim.furnish import Builder, fill_items, furniture_plan, place_furniture, scene_objects
from sim.layout import APARTMENT_SPECS, ApartmentSpec, build_structure, connect_rooms, draw_floor_plan, name_rooms
from sim.relations import compute_relations
from sim.world import (
    DOOR_H_M,
    DOOR_W_M,
    FAMILIES,
    PREDICATES,
    SCENE_FORMAT,
    SCENE_VERSION,
    WALL_T_M,
    Door,
    Room,
    Scene,
    SceneObject,
)

__all__ = [
    "APARTMENT_SPECS",
    "DOOR_H_M",
    "DOOR_W_M",
    "FAMILIES",
    "PREDICATES",
    "SCENE_FORMAT",
    "SCENE_VERSION",
    "WALL_T_M",
    "ApartmentSpec",
    "Door",
    "Room",
    "Scene",
    "SceneObject",
    "compute_relations",
    "generate_scene",
]


def generate_scene(family: str, seed: int) -> Scene:
    """Generate the scene ``(family, seed)``; the same arguments always give the same scene.

    One generator seeded by ``(seed, family)`` draws, in this order: the wall height, the floor plan and
    object count (:mod:`sim.layout`), the structure's materials and windows, each room's furniture, then the
    small items (:mod:`sim.furnish`); relations follow from the placement (:mod:`sim.relations`)."""
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family {family!r}; expected one of {FAMILIES}")
    seed = int(seed)
    rng = np.random.default_rng([seed & 0xFFFFFFFF, FAMILIES.index(family), 0xA5605])
    b = Builder(rng)
    H = round(float(rng.uniform(2.5, 2.8)), 2)
    plan = draw_floor_plan(rng, family)
    rooms = name_rooms(plan.kinds, plan.rects)
    doors = connect_rooms(plan.doors, rooms)
    smesh, sfm = build_structure(b.material, rng, plan.rects, rooms, doors, plan.size, H)
    for room in rooms:
        place_furniture(b, room, doors, furniture_plan(room.kind, family), H)
    fill_items(b, plan.n_objects, large_only=family == "furnished_room")
    objects = scene_objects(b)
    relations = compute_relations(objects, [p.surface_kind for p in b.placed])
    all_v = np.vstack([smesh.vertices] + [o.mesh.vertices for o in objects])
    return Scene(family=family, seed=seed, rooms=rooms, objects=objects, relations=relations,
                 bounds_min=all_v.min(0), bounds_max=all_v.max(0), structure=smesh,
                 structure_face_material=sfm, materials=b.materials, doors=doors, wall_height_m=H)
