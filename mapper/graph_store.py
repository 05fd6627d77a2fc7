"""The served graph: versioned nodes and edges, deltas, and query selection (pure: no I/O)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

from protocol.codec import decode, encode
from protocol.graph import edge_key
from protocol.messages import GraphDelta, GraphEdge, GraphNode, GraphSnapshot
from protocol.query import GraphQuery


class GraphStore:
    """Holds the published graph; every change becomes one :class:`GraphDelta` (version + 1).

    ``epoch`` names the version sequence (see :mod:`mapper.persistence`); every snapshot and delta carries it.
    """

    def __init__(self, epoch: str = "") -> None:
        self.epoch = epoch
        self.version = 0
        self.stamp_ns = 0
        self.nodes: dict[str, GraphNode] = {}
        self.edges: dict[tuple[str, str, str], GraphEdge] = {}
        self.changed_at: dict[str, int] = {}
        self.frames: dict[str, int] = {}  # per source, the newest frame seq processed

    def commit(
        self,
        upserted: Sequence[GraphNode],
        removed: Iterable[str],
        edges: Sequence[GraphEdge],
        stamp_ns: int,
        frames: dict[str, int] | None = None,
    ) -> GraphDelta | None:
        """Apply a change set; returns its delta, or None when nothing actually changed.

        ``edges`` is the complete new edge set (edges are recomputed as a whole after each update);
        ``frames``: the frames (source -> seq) processed for it, carried by the delta when they advance (with
        no change they are not recorded: :meth:`commit_frames` says so on its own).
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
        return GraphDelta(
            epoch=self.epoch,
            version=self.version,
            stamp_ns=stamp_ns,
            upserted=list(ups),
            removed=removed_ids,
            edges_added=added,
            edges_removed=dropped,
            frames=advanced,
        )

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

    def snapshot(self) -> GraphSnapshot:
        """The whole graph at the current version (nodes by id, edges by triple)."""
        return GraphSnapshot(
            epoch=self.epoch,
            version=self.version,
            stamp_ns=self.stamp_ns,
            nodes=[self.nodes[k] for k in sorted(self.nodes)],
            edges=[self.edges[k] for k in sorted(self.edges)],
            frames=dict(self.frames),
        )

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
        return {"snapshot": encode(self.snapshot()), "changed_at": dict(self.changed_at)}

    def load_state(self, state: dict[str, Any]) -> None:
        snap = decode(state["snapshot"], GraphSnapshot)
        self.epoch = snap.epoch
        self.version = snap.version
        self.stamp_ns = snap.stamp_ns
        self.nodes = {n.node_id: n for n in snap.nodes}
        self.edges = {edge_key(e): e for e in snap.edges}
        self.frames = dict(snap.frames)
        self.changed_at = {str(k): int(v) for k, v in state.get("changed_at", {}).items() if k in self.nodes}

    def restart_at(self, epoch: str, version: int) -> None:
        """Go on as ``version`` of ``epoch`` (a resumed mapper). When that is not the saved version, every
        node counts as changed at it: a ``since_version`` consumer gets the whole resumed graph again."""
        if version != self.version:
            self.changed_at = dict.fromkeys(self.nodes, version)
        self.epoch, self.version = epoch, version
