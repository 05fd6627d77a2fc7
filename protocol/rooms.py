"""The room layer on the wire: room nodes above the object nodes, ``in_room`` edges from objects to rooms and
``connects`` edges between rooms through a doorway.

One :class:`RoomLayer` message carries the whole layer at one graph version (rooms are few: a building has tens,
not thousands); the mapper answers it on ``graph/rooms`` (and ``graph/json/rooms``), and ``graph/nodes?room=<id>``
selects the objects in a room. A consumer that does not know this kind never receives it unless it asks.

Rooms come from the mapper's own map (mapper.rooms); their ids stay stable as the map grows into them.
"""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field

from protocol.messages import EPOCH_DESCRIPTION, MAX_EPOCH_CHARS, Message

RoomPredicate = Literal["in_room", "connects"]
ROOM_PREDICATES: tuple[str, ...] = ("in_room", "connects")
UNKNOWN_ROOM_LABEL = "unknown"


class RoomNode(Message):
    """One room of a floor."""

    KIND: ClassVar[str] = "room_node"
    room_id: str = Field(min_length=1, max_length=64, description="stable id of the room (a single key chunk), "
                         "e.g. room3; kept as the map grows into the room")
    label: str = Field(description="room kind from its objects, e.g. kitchen, bedroom, living_room; 'unknown' "
                       "until an object says something about it")
    label_confidence: float = Field(ge=0.0, le=1.0, description="posterior probability of the label (0 when unknown)")
    polygon: list[tuple[float, float]] = Field(
        description="outline, x, y in metres (world frame), counter-clockwise, not closed (last != first)")
    floor_z_m: float = Field(description="floor height, metres (world z)")
    area_m2: float = Field(ge=0.0, description="floor area, square metres")
    observed_fraction: float = Field(
        ge=0.0, le=1.0, description="share of the room's floor seen (observed floor, camera paths, object footprints)")
    centroid: tuple[float, float] = Field(description="centre of the room's floor, x, y metres (world frame)")


class RoomEdge(Message):
    """``object in_room room`` or ``room connects room`` (the latter with its doorway)."""

    KIND: ClassVar[str] = "room_edge"
    subject_id: str = Field(description="in_room: an object node id; connects: a room id")
    predicate: RoomPredicate = Field(description="in_room or connects")
    object_id: str = Field(description="a room id")
    position: tuple[float, float] | None = Field(
        default=None, description="connects: the doorway's middle, x, y metres (world frame); in_room: null")
    width_m: float | None = Field(default=None, ge=0.0, description="connects: the doorway's width; in_room: null")


class RoomLayer(Message):
    """All rooms and room edges at one graph version of one epoch."""

    KIND: ClassVar[str] = "room_layer"
    epoch: str = Field(default="", max_length=MAX_EPOCH_CHARS, description=EPOCH_DESCRIPTION)
    version: int = Field(ge=0, description="the graph version the layer was built at")
    stamp_ns: int = Field(ge=0, description="when it was built, ns since the epoch")
    rooms: list[RoomNode] = Field(default_factory=list)
    edges: list[RoomEdge] = Field(default_factory=list, description="in_room edges, then connects edges")

    def room_of(self, node_id: str) -> str | None:
        """The room id an object node is in (None: in none)."""
        return next((e.object_id for e in self.edges if e.predicate == "in_room" and e.subject_id == node_id), None)

    def members(self, room_id: str) -> list[str]:
        """Object node ids in ``room_id``."""
        return [e.subject_id for e in self.edges if e.predicate == "in_room" and e.object_id == room_id]


ROOM_MESSAGES: tuple[type[Message], ...] = (RoomNode, RoomEdge, RoomLayer)
