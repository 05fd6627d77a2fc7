"""Scene generation: determinism, content, physical plausibility, relations, serialisation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sim.catalog import CATEGORIES
from sim.check import interpenetration_issues, relation_issues, support_issues
from sim.scene import Scene, generate_scene


@pytest.fixture(scope="module")
def apt() -> Scene:
    return generate_scene("apartment", 0)


@pytest.fixture(scope="module")
def room() -> Scene:
    return generate_scene("furnished_room", 0)


def _fingerprint(scene: Scene) -> list:
    return [(o.obj_id, o.label, o.room, o.parent_id, np.asarray(o.mesh.vertices).tobytes(), o.box.center)
            for o in scene.objects]


def test_same_seed_same_scene(apt: Scene) -> None:
    again = generate_scene("apartment", 0)
    assert _fingerprint(again) == _fingerprint(apt)
    assert again.relations == apt.relations
    assert np.array_equal(again.structure.vertices, apt.structure.vertices)
    assert [m.to_dict() for m in again.materials] == [m.to_dict() for m in apt.materials]


def test_different_seeds_differ(apt: Scene) -> None:
    other = generate_scene("apartment", 1)
    assert _fingerprint(other) != _fingerprint(apt)
    assert not np.array_equal(generate_scene("furnished_room", 1).structure.vertices,
                              generate_scene("furnished_room", 2).structure.vertices)


def test_apartment_content(apt: Scene) -> None:
    assert 90 <= len(apt.objects) <= 135
    kinds = {r.kind for r in apt.rooms}
    assert {"living_room", "kitchen", "bedroom", "bathroom"} <= kinds
    assert len(apt.doors) == len(apt.rooms) - 1
    ids = [o.obj_id for o in apt.objects]
    assert ids == sorted(set(ids)) and min(ids) >= 1
    for o in apt.objects:
        assert apt.object_by_id(o.obj_id) is o
        assert o.label and o.label == o.label.lower() and "_" not in o.label
        assert any(r.name == o.room for r in apt.rooms)
        assert len(o.face_material) == len(o.mesh.faces)
        assert o.face_material.max() < len(apt.materials)
    small = [o for o in apt.objects if o.parent_id is not None]
    assert len(small) >= 40, "many small items stand on or in furniture"
    for o in small:
        assert 0.02 <= max(o.box.extent) <= 1.5
    cups = [o for o in apt.objects if o.category in ("cup", "mug", "book", "bowl")]
    for o in cups:
        assert 0.005 <= min(o.box.extent) and max(o.box.extent) <= 0.35


def test_furnished_room_content(room: Scene) -> None:
    assert len(room.rooms) == 1 and not room.doors
    assert 18 <= len(room.objects) <= 32


def test_catalog_has_many_natural_categories() -> None:
    labels = {c.label for c in CATEGORIES.values()}
    assert len(labels) >= 60
    for key in ("coffee_table", "potted_plant", "desk_lamp", "bookshelf", "laptop", "cup"):
        assert key in CATEGORIES
    for cat in CATEGORIES.values():
        m = cat.build(np.random.default_rng(0))
        lo = np.min([p.bounds[0] for p, _ in m.parts], axis=0)
        assert abs(lo[2]) < 1e-6, f"{cat.key} does not stand on z=0"
        for p, _ in m.parts:
            assert p.is_watertight, f"{cat.key} has an open part"


def test_bad_family() -> None:
    with pytest.raises(ValueError, match="family"):
        generate_scene("castle", 0)


@pytest.mark.parametrize("family", ["apartment", "furnished_room"])
def test_supported_and_not_interpenetrating(family: str, apt: Scene, room: Scene) -> None:
    scene = apt if family == "apartment" else room
    assert support_issues(scene) == []
    assert interpenetration_issues(scene) == []


def test_check_detects_a_sunk_object(apt: Scene) -> None:
    # the checks must be able to fail: sink an item 3 cm into its support
    import dataclasses

    solid = ("nightstand", "dresser", "tv_stand", "kitchen_counter", "filing_cabinet", "refrigerator")
    o = next(o for o in apt.objects if o.parent_id is not None and apt.object_by_id(o.parent_id).category in solid)
    m = o.mesh.copy()
    m.apply_translation((0.0, 0.0, -0.03))
    objs = [dataclasses.replace(x, mesh=m) if x.obj_id == o.obj_id else x for x in apt.objects]
    bad = dataclasses.replace(apt, objects=objs)
    assert any(str(o.obj_id) in s for s in support_issues(bad))
    assert interpenetration_issues(bad) != []


def test_relations_agree_with_geometry(apt: Scene) -> None:
    preds = {p for _, p, _ in apt.relations}
    assert preds == {"on_top_of", "inside", "next_to"}
    assert relation_issues(apt) == []
    for s, p, t in apt.relations:
        child, parent = apt.object_by_id(s), apt.object_by_id(t)
        if p == "on_top_of":
            assert child.parent_id == t
            # the child's bottom touches a support face of the parent at that height
            zmin = child.mesh.bounds[0, 2]
            assert any(abs(zmin - z) < 0.005 for _, z, k in parent.surfaces_world() if k == "on")
        elif p == "inside":
            assert child.parent_id == t
        else:
            assert s < t and child.room == parent.room
    # every supported object has exactly one support relation
    support = [(s, t) for s, p, t in apt.relations if p in ("on_top_of", "inside")]
    assert len(support) == sum(o.parent_id is not None for o in apt.objects)
    cats = {(apt.object_by_id(s).category, apt.object_by_id(t).category) for s, p, t in apt.relations if p == "inside"}
    assert any(c[1] in ("bookshelf", "kitchen_sink", "fruit_bowl", "bathtub", "bowl", "laundry_basket") for c in cats)


def test_json_round_trip(room: Scene) -> None:
    data = json.loads(json.dumps(room.to_json()))
    back = Scene.from_json(data)
    assert _fingerprint(back) == _fingerprint(room)
    assert back.relations == room.relations
    assert np.array_equal(back.structure_face_material, room.structure_face_material)
    with pytest.raises(ValueError):
        Scene.from_json({"format": "nope"})
