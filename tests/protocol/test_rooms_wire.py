"""The room layer's wire messages (protocol.rooms): codec round trips, hostile bytes, the JSON view."""

from __future__ import annotations

import json

import msgpack
import pytest
from hypothesis import given, settings

from protocol.codec import REGISTRY, DecodeError, content_type, decode, encode
from protocol.rooms import ROOM_MESSAGES, RoomEdge, RoomLayer, RoomNode
from tests.support.strategies import ROOM_STRATEGIES


def test_room_messages_are_registered_and_have_strategies() -> None:
    assert set(ROOM_STRATEGIES) == set(ROOM_MESSAGES)
    assert all(REGISTRY[cls.KIND] is cls for cls in ROOM_MESSAGES)
    assert content_type(RoomLayer) == "application/msgpack;argus/room_layer/1.0"


@pytest.mark.parametrize("cls", ROOM_MESSAGES, ids=lambda c: c.__name__)
def test_round_trip(cls: type) -> None:
    @settings(max_examples=25, deadline=None)
    @given(ROOM_STRATEGIES[cls])
    def check(msg) -> None:  # noqa: ANN001
        assert decode(encode(msg), cls) == msg
        assert cls.model_validate_json(msg.model_dump_json()) == msg

    check()


def test_hostile_room_layers_are_one_typed_error() -> None:
    good = encode(RoomLayer(version=1, stamp_ns=0))
    for bad in (good[:-3], msgpack.packb(["ARG1", "room_layer", 1, 0, {"version": -1, "stamp_ns": 0}]),
                msgpack.packb(["ARG1", "room_layer", 1, 0, {"version": 1, "stamp_ns": 0, "edges": [
                    {"subject_id": "n1", "predicate": "on_top_of", "object_id": "room1"}]}]),
                msgpack.packb(["ARG1", "room_layer", 2, 0, {"version": 1, "stamp_ns": 0}])):
        with pytest.raises(DecodeError):
            decode(bad, RoomLayer)


def test_a_plain_reader_sees_rooms_edges_and_doorways() -> None:
    layer = RoomLayer(version=3, stamp_ns=5, rooms=[
        RoomNode(room_id="room1", label="kitchen", label_confidence=0.9, polygon=[(0, 0), (3, 0), (3, 2)],
                 floor_z_m=0.0, area_m2=6.0, observed_fraction=0.5, centroid=(1.5, 1.0))],
        edges=[RoomEdge(subject_id="n4", predicate="in_room", object_id="room1"),
               RoomEdge(subject_id="room1", predicate="connects", object_id="room2", position=(3.0, 1.0),
                        width_m=0.9)])
    magic, kind, major, minor, body = msgpack.unpackb(encode(layer))
    assert (magic, kind, major, minor) == ("ARG1", "room_layer", 1, 0)
    assert body["rooms"][0]["polygon"][2] == [3, 2] and body["edges"][1]["position"] == [3.0, 1.0]
    assert json.loads(layer.model_dump_json())["edges"][0]["position"] is None
    assert layer.members("room1") == ["n4"] and layer.room_of("n4") == "room1"
