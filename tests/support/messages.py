"""Small wire messages built by hand for tests."""

from __future__ import annotations

from protocol.messages import GraphNode, OrientedBox


def node_msg(node_id: str, label: str = "chair", x: float = 0.0) -> GraphNode:
    return GraphNode(node_id=node_id, label=label, label_confidence=0.9, centroid=(x, 0.0, 0.0),
                     box=OrientedBox(center=(x, 0.0, 0.0), extent=(1.0, 1.0, 1.0)), point_count=1,
                     observation_count=1, first_seen_ns=0, last_seen_ns=0)
