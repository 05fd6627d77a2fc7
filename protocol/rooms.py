"""The room layer on the wire: room nodes above the object nodes, ``in_room`` edges from objects to rooms and
``connects`` edges between rooms through a doorway.

One :class:`RoomLayer` message carries the whole layer at one graph version (rooms are few: a building has tens,
not thousands); the mapper answers it on ``graph/rooms`` (and ``graph/json/rooms``), and ``graph/nodes?room=<id>``
selects the objects in a room. Since graph_snapshot / graph_delta 1.4 the layer also travels in the graph: a
snapshot carries the newest layer the mapper published, and a delta carries it when it changed (an older consumer
drops the field, as it does any newer minor's). The classes live in :mod:`protocol.messages`, beside the graph
messages that carry them; this module names them for the room layer's users.

Rooms come from the mapper's own map (mapper.rooms); their ids stay stable as the map grows into them.
"""

from __future__ import annotations

from protocol.messages import ROOM_PREDICATES, Message, RoomEdge, RoomLayer, RoomNode, RoomPredicate

UNKNOWN_ROOM_LABEL = "unknown"

__all__ = ["ROOM_MESSAGES", "ROOM_PREDICATES", "UNKNOWN_ROOM_LABEL", "RoomEdge", "RoomLayer", "RoomNode",
           "RoomPredicate"]

ROOM_MESSAGES: tuple[type[Message], ...] = (RoomNode, RoomEdge, RoomLayer)
