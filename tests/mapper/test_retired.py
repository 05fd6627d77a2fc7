"""Moves and retired nodes in the served graph (mapper.graph_store) and on the wire (graph_snapshot and
graph_delta 1.3, node_move, retired_node, the include_retired selector)."""

from __future__ import annotations

import msgpack
import pytest

from mapper.graph_store import GraphStore
from protocol.codec import decode, encode
from protocol.messages import GraphDelta, GraphNode, GraphSnapshot, NodeMove, OrientedBox
from protocol.query import GraphQuery


def node(node_id: str, label: str = "chair", x: float = 0.0) -> GraphNode:
    return GraphNode(node_id=node_id, label=label, label_confidence=0.9, centroid=(x, 0.0, 0.4),
                     box=OrientedBox(center=(x, 0.0, 0.4), extent=(0.5, 0.5, 0.8)), point_count=100,
                     observation_count=3, sources=["cam1"], first_seen_ns=1, last_seen_ns=2)


def move(node_id: str, stamp_ns: int, x0: float, x1: float) -> NodeMove:
    return NodeMove(node_id=node_id, stamp_ns=stamp_ns, from_centroid=(x0, 0.0, 0.4), to_centroid=(x1, 0.0, 0.4))


def store_with_changes(**kw: float) -> GraphStore:
    s = GraphStore("E", **kw)  # type: ignore[arg-type]
    s.commit([node("n1"), node("n2", "lamp", 2.0)], [], [], 10)
    s.commit([node("n1", x=1.0)], [], [], 20, moves=[move("n1", 20, 0.0, 1.0)])
    return s


class TestStore:
    def test_a_move_is_in_the_delta_and_the_node_keeps_it(self) -> None:
        s = GraphStore("E")
        s.commit([node("n1")], [], [], 10)
        d = s.commit([node("n1", x=1.0)], [], [], 20, moves=[move("n1", 20, 0.0, 1.0), move("n9", 20, 0, 1)])
        assert d is not None and [m.node_id for m in d.moves] == ["n1"] and d.upserted[0].centroid[0] == 1.0
        assert [m.stamp_ns for m in s.snapshot().moves] == [20]

    def test_a_retired_node_leaves_the_graph_with_a_record(self) -> None:
        s = store_with_changes()
        d = s.commit([], ["n1"], [], 30, retired={"n1": node("n1", x=1.0)})
        assert d is not None and d.removed == ["n1"] and len(d.retired) == 1
        r = d.retired[0]
        assert (r.node.node_id, r.retired_ns, r.version, r.reason, r.last_moved_ns) == ("n1", 30, 3, "absent", 20)
        snap = s.snapshot()
        assert [n.node_id for n in snap.nodes] == ["n2"] and snap.moves == [] and snap.retired == []
        assert [r.node.node_id for r in s.snapshot(with_retired=True).retired] == ["n1"]

    def test_merged_or_pruned_nodes_have_no_record(self) -> None:
        s = store_with_changes()
        d = s.commit([], ["n2"], [], 30)
        assert d is not None and d.removed == ["n2"] and d.retired == [] and not s.retired

    def test_the_selection_applies_to_retired_nodes(self) -> None:
        s = store_with_changes()
        s.commit([], ["n1"], [], 30, retired={"n1": node("n1", x=1.0)})
        s.commit([], ["n2"], [], 40, retired={"n2": node("n2", "lamp", 2.0)})
        assert [r.node.node_id for r in s.retired_matching(GraphQuery())] == ["n2", "n1"]  # newest first
        assert [r.node.node_id for r in s.retired_matching(GraphQuery(label="chair"))] == ["n1"]
        assert [r.node.node_id for r in s.retired_matching(GraphQuery(near=(2.0, 0.0, 0.4), radius=0.5))] == ["n2"]
        assert [r.node.node_id for r in s.retired_matching(GraphQuery(since_version=3))] == ["n2"]

    def test_the_history_is_bounded_in_count_and_time(self) -> None:
        s = GraphStore("E", max_retired=2, retired_keep_s=1.0)
        ids = [f"n{i}" for i in range(4)]
        s.commit([node(i) for i in ids], [], [], 0)
        for t, i in enumerate(ids[:3]):
            s.commit([], [i], [], 10 + t, retired={i: node(i)})
        assert list(s.retired) == ["n1", "n2"]
        s.commit([], ["n3"], [], int(2e9), retired={"n3": node("n3")})
        assert list(s.retired) == ["n3"]

    def test_state_round_trip(self) -> None:
        s = store_with_changes()
        s.commit([], ["n2"], [], 30, retired={"n2": node("n2", "lamp", 2.0)})
        again = GraphStore()
        again.load_state(s.state())
        assert again.moves == s.moves and list(again.retired) == ["n2"] and again.retired["n2"] == s.retired["n2"]
        assert again.snapshot() == s.snapshot()


def test_a_follower_rebuilds_the_mappers_snapshot_moves_included() -> None:
    from protocol.graph import apply_delta

    s = GraphStore("E")
    s.commit([node("n1"), node("n2", "lamp", 2.0)], [], [], 10)
    followed = s.snapshot()
    for args in (([node("n1", x=1.0)], [], [], 20, None, [move("n1", 20, 0.0, 1.0)]),
                 ([node("n2", "lamp", 3.0)], [], [], 30, None, [move("n2", 30, 2.0, 3.0)]),
                 ([], ["n1"], [], 40, None, (), {"n1": node("n1", x=1.0)})):
        d = s.commit(*args)  # type: ignore[arg-type]
        assert d is not None
        followed = apply_delta(followed, d)
        assert followed == s.snapshot()
    assert [m.node_id for m in followed.moves] == ["n2"]


class TestWire:
    def test_include_retired_parses_and_round_trips(self) -> None:
        for text, flag in (("true", True), ("1", True), ("false", False), ("no", False)):
            q = GraphQuery.from_parameters(f"label=cup;include_retired={text}")
            assert q.include_retired is flag and GraphQuery.from_parameters(q.to_parameters()) == q
        with pytest.raises(ValueError, match="include_retired"):
            GraphQuery.from_parameters("include_retired=maybe")

    def test_snapshot_and_delta_round_trip(self) -> None:
        s = store_with_changes()
        d = s.commit([], ["n1"], [], 30, retired={"n1": node("n1", x=1.0)})
        assert d is not None and decode(encode(d), GraphDelta) == d
        snap = s.snapshot(with_retired=True)
        assert decode(encode(snap), GraphSnapshot) == snap
        assert GraphSnapshot.model_validate_json(snap.model_dump_json()) == snap

    def test_a_reader_of_schema_1_2_reads_1_3_and_later(self) -> None:
        """Everything new in 1.3 (moves, retired) is top-level (a 1.2 reader drops it, as the versioning rules
        ask) or a new kind: the nodes inside keep graph_node 1.0's fields, which a strict reader needs."""
        old_snapshot = {"epoch", "version", "stamp_ns", "nodes", "edges", "frames"}
        old_delta = {"epoch", "version", "stamp_ns", "upserted", "removed", "edges_added", "edges_removed", "frames"}
        node_1_0 = set(GraphNode.model_fields)
        assert GraphNode.SCHEMA == (1, 0)
        s = store_with_changes()
        d = s.commit([node("n2", "lamp", 2.5)], ["n1"], [], 30, retired={"n1": node("n1", x=1.0)})
        assert d is not None
        for msg, old in ((s.snapshot(with_retired=True), old_snapshot), (d, old_delta)):
            _, _, major, minor, body = msgpack.unpackb(encode(msg), raw=False)
            assert major == 1 and minor >= 3 and {"moves", "retired"} <= set(body) - old
            for n in body.get("nodes", []) + body.get("upserted", []):
                assert set(n) == node_1_0
            stripped = {k: v for k, v in body.items() if k in old}
            assert type(msg).model_validate(stripped).version == msg.version
