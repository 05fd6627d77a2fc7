"""Apply graph deltas to snapshots: the one consumer-side rule for following the live graph.

A consumer (``argus query``, the planner, a viewer) takes one :class:`GraphSnapshot` and then applies
each :class:`GraphDelta` in version order; :class:`GraphFollower` is that rule with mapper restarts
(epochs) and forged or stale snapshots handled. Pure, no I/O.
"""

from __future__ import annotations

from protocol.messages import GraphDelta, GraphEdge, GraphSnapshot


class GraphVersionError(ValueError):
    """A delta that does not follow the snapshot (another epoch, or ``delta.version != snapshot.version + 1``)."""


def edge_key(edge: GraphEdge) -> tuple[str, str, str]:
    """``(subject_id, predicate, object_id)``: edges are identified by this triple."""
    return (edge.subject_id, edge.predicate, edge.object_id)


def apply_delta(snapshot: GraphSnapshot, delta: GraphDelta) -> GraphSnapshot:
    """The graph after ``delta``; raises :class:`GraphVersionError` when versions do not follow.

    Nodes are upserted by id and removed by id; edges are removed and added by their triple, and
    edges left dangling by a removed node are dropped; each node's last move is the delta's, else the
    snapshot's (schema 1.3), and a removed node's is dropped; the room layer is the delta's when it carries one,
    else the snapshot's (schema 1.4). Nodes come out sorted by id and edges by
    their triple, the order the mapper uses, so a snapshot rebuilt from deltas compares equal to
    the mapper's own snapshot of the same version.
    """
    if delta.epoch != snapshot.epoch:
        raise GraphVersionError(f"delta of epoch {delta.epoch!r} does not follow snapshot epoch {snapshot.epoch!r}")
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
    moves = {m.node_id: m for m in snapshot.moves}
    moves.update((m.node_id, m) for m in delta.moves)
    return GraphSnapshot(
        epoch=delta.epoch,
        version=delta.version,
        stamp_ns=delta.stamp_ns,
        nodes=[nodes[k] for k in sorted(nodes)],
        edges=kept,
        frames={**snapshot.frames, **delta.frames},
        moves=[moves[k] for k in sorted(moves) if k in nodes],
        rooms=delta.rooms if delta.rooms is not None else snapshot.rooms,
    )


RESYNC_AFTER = 3
"""Stale snapshots (same epoch, older version) in a row after which a follower adopts the newest of them."""


class GraphFollower:
    """Follows the live graph from snapshots and deltas, whatever the mapper or the network does.

    The rule (also in docs/consumers.md, "Graph versions, epochs and mapper restarts", and docs/WIRE.md):

    1. A snapshot is adopted when its epoch differs from the followed graph's (a new mapper life) or when
       its version is at least the followed one's.
    2. A snapshot of the same epoch but an older version is *stale*. When ``resync_after`` stale snapshots
       arrive in a row (no snapshot adopted, no delta applied between them), the newest of them is adopted:
       a mapper that keeps publishing a graph older than ours means ours is not its graph (a forged
       snapshot with a huge version, or a mapper that lost the versions it had reserved).
    3. A delta is applied when it has the followed epoch and the next version. A delta of another epoch,
       a gap, or ``resync_after`` stale deltas in a row set :attr:`need_snapshot`: the caller re-queries
       the snapshot (each reply offered here; stale replies count for rule 2).

    A forger that keeps publishing can still make a follower flap; only the router's ACL (the mapper alone
    may put ``graph/**``) prevents that. Not thread-safe: one owner calls it.
    """

    def __init__(self, resync_after: int = RESYNC_AFTER) -> None:
        self.resync_after = resync_after
        self.graph = GraphSnapshot(version=0, stamp_ns=0)
        self.need_snapshot = True
        self.counters: dict[str, int] = {}
        self._stale: GraphSnapshot | None = None
        self._stale_snapshots = 0
        self._stale_deltas = 0

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    def _adopt(self, snap: GraphSnapshot) -> None:
        if snap.epoch != self.graph.epoch:
            self._count("epoch_changes")
        self.graph = snap
        self.need_snapshot = False
        self._stale, self._stale_snapshots, self._stale_deltas = None, 0, 0

    def offer_snapshot(self, snap: GraphSnapshot) -> str:
        """Offer one snapshot; returns what became of it: ``adopted``, ``resynced`` or ``stale``."""
        if snap.epoch != self.graph.epoch or snap.version >= self.graph.version:
            self._adopt(snap)
            return "adopted"
        self._count("snapshots_stale")
        self._stale_snapshots += 1
        if self._stale is None or snap.version >= self._stale.version:
            self._stale = snap
        if self._stale_snapshots < self.resync_after:
            return "stale"
        self._count("resyncs")
        self._adopt(self._stale)
        return "resynced"

    def offer_delta(self, delta: GraphDelta) -> str:
        """Offer one delta; returns ``applied``, ``old`` (already covered), ``other_epoch`` or ``gap``."""
        if delta.epoch != self.graph.epoch:
            self._count("delta_gaps")  # it does not follow either
            self._count("deltas_other_epoch")
            self.need_snapshot = True
            return "other_epoch"
        if delta.version <= self.graph.version:
            self._stale_deltas += 1
            if self._stale_deltas >= self.resync_after:
                self.need_snapshot = True
            return "old"
        if delta.version != self.graph.version + 1:
            self._count("delta_gaps")
            self.need_snapshot = True
            return "gap"
        self.graph = apply_delta(self.graph, delta)
        self._stale, self._stale_snapshots, self._stale_deltas = None, 0, 0
        return "applied"
