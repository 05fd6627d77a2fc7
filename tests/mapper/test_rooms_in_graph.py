"""The room layer travels in the graph (graph_snapshot / graph_delta 1.4): a changed layer goes out in a delta,
snapshots carry the newest one published, and a consumer that applies the deltas holds what a snapshot says."""

from __future__ import annotations

from mapper.graph_store import GraphStore
from protocol.graph import apply_delta
from protocol.messages import GraphSnapshot
from protocol.rooms import RoomEdge, RoomLayer, RoomNode
from tests.support.boxes import EYES, oracle_core, view
from tests.support.floorplans import node


def layer(label: str = "bedroom", members: tuple[str, ...] = ("a",)) -> RoomLayer:
    room = RoomNode(room_id="room1", label=label, label_confidence=0.8, polygon=[(0, 0), (4, 0), (4, 4), (0, 4)],
                    floor_z_m=0.0, area_m2=16.0, observed_fraction=0.9, centroid=(2.0, 2.0))
    return RoomLayer(version=0, stamp_ns=5, rooms=[room],
                     edges=[RoomEdge(subject_id=m, predicate="in_room", object_id="room1") for m in members])


def test_a_changed_layer_is_one_delta_and_an_unchanged_one_none() -> None:
    store = GraphStore(epoch="E")
    first = store.commit([node("a", "bed", 1.0, 1.0)], [], [], 1)
    assert first is not None and first.rooms is None and first.version == 1
    carried = store.commit_rooms(layer(), 2, first)  # built at this keyframe's version: rides on its delta
    assert carried is not None and carried.version == 1 and carried.rooms is not None
    assert carried.rooms.version == 1 and carried.rooms.epoch == "E" and store.version == 1
    assert store.commit_rooms(layer().model_copy(update={"stamp_ns": 9}), 3) is None  # same rooms: nothing
    own = store.commit_rooms(layer("kitchen"), 4)  # relabelled with no other change: a delta of its own
    assert own is not None and own.version == 2 and own.rooms is not None and own.rooms.rooms[0].label == "kitchen"
    assert not own.upserted and not own.removed
    snap = apply_delta(apply_delta(GraphSnapshot(epoch="E", version=0, stamp_ns=0), carried), own)
    assert snap == store.snapshot() and snap.rooms == own.rooms


def test_rooms_survive_a_restart_of_the_store() -> None:
    store = GraphStore(epoch="E")
    store.commit_rooms(layer(), 1)
    again = GraphStore()
    again.load_state(store.state())
    assert again.snapshot().rooms == store.snapshot().rooms and again.rooms is not None
    assert again.commit_rooms(layer(), 2) is None  # what it published before the restart: not sent again


def test_a_mapper_publishes_its_rooms_in_the_deltas_it_sends() -> None:
    core = oracle_core()
    core.config.rooms.every_keyframes = 2  # rebuilt twice over the four views
    snap = GraphSnapshot(version=0, stamp_ns=0)
    with_rooms = 0
    for i, eye in enumerate(EYES):
        delta = core.ingest(view(eye, i))
        if delta is not None:
            with_rooms += delta.rooms is not None
            snap = apply_delta(snap, delta)
    assert with_rooms >= 1 and snap.rooms is not None
    assert snap == core.snapshot()  # deltas and snapshot agree, rooms included
