"""The ``apartment_large`` family: more rooms and objects than ``apartment``, deterministic, every room reachable."""

from __future__ import annotations

import math
from typing import get_args

import numpy as np
import pytest

from sim.check import nav_issues, relation_issues, support_issues
from sim.config import Family
from sim.nav import NavMap
from sim.scene import APARTMENT_SPECS, FAMILIES, Scene, generate_scene


@pytest.fixture(scope="module")
def large() -> list[Scene]:
    return [generate_scene("apartment_large", s) for s in (0, 1, 2)]


def test_families_listed_alike_for_the_clis() -> None:
    assert set(get_args(Family)) == set(FAMILIES)
    assert FAMILIES[:2] == ("apartment", "furnished_room")  # the index seeds the generator: append only


def test_existing_apartments_unchanged() -> None:
    """Adding the family must not move the apartments every earlier figure was measured on."""
    counts = [(len(s.rooms), len(s.objects)) for s in (generate_scene("apartment", k) for k in range(3))]
    assert counts == [(6, 118), (6, 101), (6, 119)]


def test_large_apartments_have_more_rooms_and_objects(large: list[Scene]) -> None:
    spec = APARTMENT_SPECS["apartment_large"]
    for k, scene in enumerate(large):
        small = generate_scene("apartment", k)
        assert len(scene.rooms) in spec.rooms and len(scene.rooms) > len(small.rooms)
        assert spec.objects[0] <= len(scene.objects) <= spec.objects[1]
        assert len(scene.objects) >= 1.25 * len(small.objects)
        w, d = (scene.bounds_max - scene.bounds_min)[:2]
        assert max(w, d) >= spec.width_m[0] and min(w, d) >= spec.depth_m[0] - 0.5
        kinds = {r.kind for r in scene.rooms}
        assert {"living_room", "kitchen", "bedroom", "bathroom", "dining_room"} <= kinds
    assert [len(s.objects) for s in large] == [161, 167, 150]  # the per-seed counts the README quotes


def test_large_apartment_is_deterministic_per_seed(large: list[Scene]) -> None:
    again = generate_scene("apartment_large", 1)
    assert [(o.label, o.room, o.box.center) for o in again.objects] == [
        (o.label, o.room, o.box.center) for o in large[1].objects
    ]
    assert [(o.label, o.box.center) for o in large[0].objects] != [(o.label, o.box.center) for o in large[1].objects]


def test_every_room_reachable_and_objects_supported(large: list[Scene]) -> None:
    for scene in large:
        nav = NavMap(scene)
        assert nav_issues(scene, nav) == []
        reps = {}
        for r in scene.rooms:
            cells = nav.room_cells(r)
            assert len(cells) > 20, f"{scene.seed} {r.name} has no reachable floor"
            reps[r.name] = tuple(np.asarray(cells[len(cells) // 2], float))
        first = reps[scene.rooms[0].name]
        for name, xy in reps.items():
            assert math.isfinite(nav.geodesic(first, xy)), f"seed {scene.seed}: {name} cut off"
        assert support_issues(scene) == []
        assert relation_issues(scene) == []
