"""Apply graph deltas to snapshots: the one consumer-side rule for following the live graph.

A consumer (``argus query``, the planner, a viewer) takes one :class:`GraphSnapshot` and then applies
each :class:`GraphDelta` in version order. Pure functions, no I/O.
"""

from __future__ import annotations

from protocol.messages import GraphDelta, GraphEdge, GraphSnapshot


class GraphVersionError(ValueError):
    """A delta that does not follow the snapshot (``delta.version != snapshot.version + 1``)."""


def edge_key(edge: GraphEdge) -> tuple[str, str, str]:
    """``(subject_id, predicate, object_id)``: edges are identified by this triple."""
    return (edge.subject_id, edge.predicate, edge.object_id)


def apply_delta(snapshot: GraphSnapshot, delta: GraphDelta) -> GraphSnapshot:
    """The graph after ``delta``; raises :class:`GraphVersionError` when versions do not follow.

    Nodes are upserted by id and removed by id; edges are removed and added by their triple, and
    edges left dangling by a removed node are dropped. Nodes come out sorted by id and edges by
    their triple, the order the mapper uses, so a snapshot rebuilt from deltas compares equal to
    the mapper's own snapshot of the same version.
    """
    if delta.version != snapshot.version + 1:
        raise GraphVersionError(f"delta version {delta.version} does not follow snapshot version {snapshot.version}")
    nodes = {n.node_id: n for n in snapshot.nodes}
    for node_id in delta.removed:
        nodes.pop(node_id, None)
    for node in delta.upserted:
        nodes[node.node_id] = node
    edges = {edge_key(e): e for e in snapshot.edges}
    for e in delta.edges_removed:
        edges.pop(edge_key(e), None)
    for e in delta.edges_added:
        edges[edge_key(e)] = e
    kept = [e for k, e in sorted(edges.items()) if e.subject_id in nodes and e.object_id in nodes]
    return GraphSnapshot(
        version=delta.version,
        stamp_ns=delta.stamp_ns,
        nodes=[nodes[k] for k in sorted(nodes)],
        edges=kept,
        frames={**snapshot.frames, **delta.frames},
    )
