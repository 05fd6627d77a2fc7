"""bench.rooms: the room scoring against true rooms, on a generated two-room plan (no episodes)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bench.rooms import score_rooms, synthetic_map
from mapper.rooms import RoomMapper
from tests.support.floorplans import NODES, node, two_rooms


def _room(name: str, kind: str, x0: float, x1: float) -> SimpleNamespace:
    r = SimpleNamespace(name=name, kind=kind, xy_min=np.array([x0, 0.0]), xy_max=np.array([x1, 4.0]))
    r.contains = lambda x, y: x0 <= x <= x1 and 0.0 <= y <= 4.0
    return r


def _scene() -> SimpleNamespace:
    rooms = [_room("bedroom", "bedroom", 0.0, 4.0), _room("kitchen", "kitchen", 4.1, 8.0)]
    return SimpleNamespace(rooms=rooms, doors=[object()],
                           room_at=lambda x, y: next((r for r in rooms if r.contains(x, y)), None))


def test_score_of_a_right_answer() -> None:
    rm = RoomMapper()
    layer = rm.update(two_rooms(), NODES)
    s = score_rooms(layer, rm.in_room, NODES, _scene())
    assert s["rooms_pred"] == s["rooms_true"] == 2
    assert s["iou"] > 0.9 and s["assign_acc"] == 1.0 and s["label_acc"] == 1.0
    assert s["doorways_pred"] == s["doorways_true"] == 1


def test_score_counts_wrong_assignments_and_labels() -> None:
    rm = RoomMapper()
    nodes = [node("a", "refrigerator", 1.5, 2.0), node("b", "stove", 2.5, 1.0), node("c", "chair", 6.0, 2.0)]
    layer = rm.update(two_rooms(), nodes)
    rm.in_room["c"] = rm.in_room["a"]  # one object put in the wrong room
    s = score_rooms(layer, rm.in_room, nodes, _scene())
    assert s["assign_acc"] == pytest.approx(2 / 3)
    assert s["label_acc"] == 0.0  # the bedroom looks like a kitchen, the kitchen says nothing


def test_synthetic_map_has_the_rooms_it_was_built_with() -> None:
    pts, cams, nodes = synthetic_map(np.random.default_rng(0), rooms_x=2, rooms_y=1, n_points=40_000, n_objects=20)
    rm = RoomMapper()
    for c in cams:
        rm.note_camera(c)
    layer = rm.update(pts, nodes)
    assert len(layer.rooms) == 2 and len(layer.doorways) == 1 and len(rm.in_room) == 20
