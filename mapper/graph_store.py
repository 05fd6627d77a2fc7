"""The served graph: versioned nodes and edges, deltas, and query selection (pure: no I/O).

Besides the live graph it keeps each node's last move (:class:`NodeMove`) and the nodes retired because their
place was seen empty (:class:`RetiredNode`): the newest ``max_retired``, for ``retired_keep_s`` seconds of
capture time, answered to ``include_retired`` queries."""

from __future__ import annotations

import collections
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from protocol.codec import decode, encode
from protocol.graph import edge_key
from protocol.messages import GraphDelta, GraphEdge, GraphNode, GraphSnapshot, NodeMove, RetiredNode, RoomLayer
from protocol.query import GraphQuery


class GraphStore:
    """Holds the published graph; every change becomes one :class:`GraphDelta` (version + 1).

    ``epoch`` names the version sequence (see :mod:`mapper.persistence`); every snapshot and delta carries it.
    """

    def __init__(self, epoch: str = "", max_retired: int = 256, retired_keep_s: float = 3600.0) -> None:
        self.epoch = epoch
        self.max_retired = max_retired
        self.retired_keep_ns = int(retired_keep_s * 1e9)
        self.moves: dict[str, NodeMove] = {}  # per live node that ever moved, its last move
        self.retired: collections.OrderedDict[str, RetiredNode] = collections.OrderedDict()  # oldest first
        self.version = 0
        self.stamp_ns = 0
        self.nodes: dict[str, GraphNode] = {}
        self.edges: dict[tuple[str, str, str], GraphEdge] = {}
        self.changed_at: dict[str, int] = {}
        self.frames: dict[str, int] = {}  # per source, the newest frame seq processed
        self.rooms: RoomLayer | None = None  # the room layer the deltas carried last (snapshots carry it)

    def commit(
        self,
        upserted: Sequence[GraphNode],
        removed: Iterable[str],
        edges: Sequence[GraphEdge],
        stamp_ns: int,
        frames: dict[str, int] | None = None,
        moves: Sequence[NodeMove] = (),
        retired: Mapping[str, GraphNode] | None = None,
    ) -> GraphDelta | None:
        """Apply a change set; returns its delta, or None when nothing actually changed.

        ``edges`` is the complete new edge set (edges are recomputed as a whole after each update);
        ``frames``: the frames (source -> seq) processed for it, carried by the delta when they advance (with
        no change they are not recorded: :meth:`commit_frames` says so on its own). ``moves``: the moves of
        upserted nodes; ``retired``: of ``removed``, the nodes retired because seen gone, as they were then.
        """
        removed_ids = sorted({r for r in removed if r in self.nodes})
        gone = set(removed_ids)
        ups = sorted(
            (n for n in upserted if n.node_id not in gone and self.nodes.get(n.node_id) != n),
            key=lambda n: n.node_id,
        )
        alive = (set(self.nodes) - gone) | {n.node_id for n in ups}
        new_edges = {edge_key(e): e for e in edges if e.subject_id in alive and e.object_id in alive}
        added = [e for k, e in sorted(new_edges.items()) if k not in self.edges]
        dropped = [e for k, e in sorted(self.edges.items()) if k not in new_edges]
        if not (ups or removed_ids or added or dropped):
            return None
        advanced = self._advance(frames)
        self.version += 1
        self.stamp_ns = stamp_ns
        for node_id in removed_ids:
            del self.nodes[node_id]
            self.changed_at.pop(node_id, None)
        for n in ups:
            self.nodes[n.node_id] = n
            self.changed_at[n.node_id] = self.version
        self.edges = new_edges
        alive_ups = {n.node_id for n in ups}
        moved = sorted((m for m in moves if m.node_id in alive_ups), key=lambda m: m.node_id)
        self.moves.update((m.node_id, m) for m in moved)
        records = []
        for node_id in removed_ids:
            last = self.moves.pop(node_id, None)
            node = (retired or {}).get(node_id)
            if node is not None:
                records.append(RetiredNode(node=node, retired_ns=stamp_ns, version=self.version,
                                           last_moved_ns=last.stamp_ns if last is not None else 0))
        self._keep_retired(records, stamp_ns)
        return GraphDelta(
            epoch=self.epoch,
            version=self.version,
            stamp_ns=stamp_ns,
            upserted=list(ups),
            removed=removed_ids,
            edges_added=added,
            edges_removed=dropped,
            frames=advanced,
            moves=moved,
            retired=records,
        )

    def _keep_retired(self, records: Sequence[RetiredNode], stamp_ns: int) -> None:
        """Remember ``records``; forget the oldest beyond ``max_retired`` or ``retired_keep_ns`` old."""
        for r in records:
            self.retired.pop(r.node.node_id, None)
            self.retired[r.node.node_id] = r
        while self.retired and (len(self.retired) > self.max_retired or next(iter(
                self.retired.values())).retired_ns < stamp_ns - self.retired_keep_ns):
            self.retired.popitem(last=False)

    def _advance(self, frames: dict[str, int] | None) -> dict[str, int]:
        advanced = {k: int(v) for k, v in (frames or {}).items() if int(v) > self.frames.get(k, -1)}
        self.frames.update(advanced)
        return advanced

    def commit_frames(self, frames: dict[str, int], stamp_ns: int) -> GraphDelta | None:
        """A delta that only says these frames were processed (they changed nothing), when they advance: a
        planner waiting for a robot's arrival frame learns the graph it has already covers it."""
        advanced = self._advance(frames)
        if not advanced:
            return None
        self.version += 1
        self.stamp_ns = stamp_ns
        return GraphDelta(epoch=self.epoch, version=self.version, stamp_ns=stamp_ns, frames=advanced)

    def commit_rooms(self, layer: RoomLayer, stamp_ns: int, delta: GraphDelta | None = None) -> GraphDelta | None:
        """Publish a rebuilt room layer when it differs from the one published (rooms, labels, edges; its version
        and stamp aside): carried by ``delta`` (the change set just committed, whose version the layer was built
        at) when one is given, else by a delta of its own (version + 1). Returns the delta that carries it
        (``delta`` updated, or the new one), ``delta`` itself when the layer is unchanged."""
        old = self.rooms
        if old is not None and old.epoch == self.epoch and (old.rooms, old.edges) == (layer.rooms, layer.edges):
            return delta
        if delta is None:
            self.version += 1
            self.stamp_ns = stamp_ns
            delta = GraphDelta(epoch=self.epoch, version=self.version, stamp_ns=stamp_ns)
        self.rooms = layer.model_copy(update={"epoch": self.epoch, "version": delta.version})
        return delta.model_copy(update={"rooms": self.rooms})

    def snapshot(self, with_retired: bool = False) -> GraphSnapshot:
        """The whole graph at the current version (nodes by id, edges by triple, the last move of every node
        that moved); ``with_retired``: the retired nodes too (newest first)."""
        retired = list(reversed(self.retired.values())) if with_retired else []
        return GraphSnapshot(
            epoch=self.epoch,
            version=self.version,
            stamp_ns=self.stamp_ns,
            nodes=[self.nodes[k] for k in sorted(self.nodes)],
            edges=[self.edges[k] for k in sorted(self.edges)],
            frames=dict(self.frames),
            moves=self.moves_of(self.nodes),
            retired=retired,
            rooms=self.rooms,
        )

    def moves_of(self, ids: Iterable[str]) -> list[NodeMove]:
        """The last moves of the live nodes ``ids`` that ever moved, by id (a retired node's last move time is
        in its record)."""
        return sorted((self.moves[k] for k in set(ids) if k in self.moves), key=lambda m: m.node_id)

    def retired_matching(self, q: GraphQuery) -> list[RetiredNode]:
        """The retired nodes ``q`` selects (its node parameters; ``since_version``: retired after it), newest
        first."""
        out = [r for r in reversed(self.retired.values()) if q.matches(r.node)]
        if q.since_version is not None:
            out = [r for r in out if r.version > q.since_version]
        return out

    def query(self, q: GraphQuery) -> list[GraphNode]:
        """Nodes selected by ``q`` (``since_version``: changed after that version), sorted by id."""
        if q.id is not None:
            cands: list[GraphNode] = [self.nodes[q.id]] if q.id in self.nodes else []
        else:
            cands = [self.nodes[k] for k in sorted(self.nodes)]
        out = [n for n in cands if q.matches(n)]
        if q.since_version is not None:
            out = [n for n in out if self.changed_at.get(n.node_id, 0) > q.since_version]
        return out

    # -- persistence --------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        snap = self.snapshot(with_retired=True)
        return {"snapshot": encode(snap), "changed_at": dict(self.changed_at)}

    def load_state(self, state: dict[str, Any]) -> None:
        snap = decode(state["snapshot"], GraphSnapshot)
        # states written before schema 1.3 have neither: no moves, nothing retired
        self.moves = {m.node_id: m for m in snap.moves if m.node_id in {n.node_id for n in snap.nodes}}
        self.retired = collections.OrderedDict((r.node.node_id, r) for r in reversed(snap.retired))
        self.epoch = snap.epoch
        self.version = snap.version
        self.stamp_ns = snap.stamp_ns
        self.nodes = {n.node_id: n for n in snap.nodes}
        self.edges = {edge_key(e): e for e in snap.edges}
        self.frames = dict(snap.frames)
        self.rooms = snap.rooms  # states written before schema 1.4 have none: the next build publishes one
        self.changed_at = {str(k): int(v) for k, v in state.get("changed_at", {}).items() if k in self.nodes}

    def restart_at(self, epoch: str, version: int) -> None:
        """Go on as ``version`` of ``epoch`` (a resumed mapper). When that is not the saved version, every
        node counts as changed at it: a ``since_version`` consumer gets the whole resumed graph again."""
        if version != self.version:
            self.changed_at = dict.fromkeys(self.nodes, version)
        self.epoch, self.version = epoch, version
