"""What the mapper sends out (mapper/outbox.py): a delta with its node keys, and the snapshot and point map
only when the graph changed and their period has passed."""

from __future__ import annotations

import types
from typing import Any

import numpy as np

from mapper.config import MapperConfig
from mapper.outbox import GraphOutbox
from protocol.codec import decode
from protocol.keys import Keys
from protocol.messages import GraphDelta, GraphNode, GraphSnapshot, PointMap
from protocol.transport import Counters
from tests.support.messages import node_msg

KEYS = Keys("outbox")


class Sink:
    def __init__(self) -> None:
        self.puts: list[tuple[Any, ...]] = []

    def put(self, *args: Any, **kw: Any) -> None:
        self.puts.append(args)

    def delete(self, key: str) -> None:
        self.puts.append(("delete", key))


class FakeCore:
    """The parts of MapperCore the outbox reads."""

    def __init__(self) -> None:
        self.epoch, self.version, self.voxels = "e1", 0, np.zeros((0, 3))

    def snapshot(self) -> GraphSnapshot:
        return GraphSnapshot(epoch=self.epoch, version=self.version, stamp_ns=1)

    def point_map(self, max_points: int) -> PointMap:
        return PointMap(version=self.version, stamp_ns=1, voxel_m=0.05, points=np.asarray(self.voxels, np.float32))


def outbox(snapshot_period_s: float = 2.0) -> tuple[GraphOutbox, FakeCore, Sink, dict[str, Sink]]:
    core = FakeCore()
    config = MapperConfig(site="outbox", publish={"snapshot_period_s": snapshot_period_s, "point_map_period_s": 60.0})
    box = GraphOutbox(core, config, KEYS, Counters())  # type: ignore[arg-type]
    session, pubs = Sink(), {"delta": Sink(), "snapshot": Sink(), "map": Sink()}
    box.session, box.pubs = session, pubs  # what open(node) declares
    return box, core, session, pubs


def test_a_delta_goes_out_with_each_changed_node_under_its_key_and_removed_ones_deleted() -> None:
    box, _, session, pubs = outbox()
    box.delta(GraphDelta(epoch="e1", version=2, stamp_ns=1, upserted=[node_msg("n1"), node_msg("n2")], removed=["n0"]))
    assert decode(pubs["delta"].puts[0][0], GraphDelta).version == 2
    assert [p[0] for p in session.puts] == [KEYS.graph_node("n1"), KEYS.graph_node("n2"), "delete"]
    assert session.puts[2] == ("delete", KEYS.graph_node("n0"))
    assert decode(session.puts[0][1], GraphNode).node_id == "n1" and box.counters.get("deltas") == 1


def test_the_snapshot_goes_out_once_per_change_and_period() -> None:
    box, core, _, pubs = outbox(snapshot_period_s=3600.0)
    box.periodic(force=True)  # at start: even version 0
    assert len(pubs["snapshot"].puts) == 1 and pubs["map"].puts == []  # no voxels: no point map
    box.periodic(force=True)
    assert len(pubs["snapshot"].puts) == 1  # nothing changed
    core.version = 1
    box.periodic()
    assert len(pubs["snapshot"].puts) == 1  # changed, but within the period
    box.periodic(force=True)
    assert len(pubs["snapshot"].puts) == 2 and decode(pubs["snapshot"].puts[1][0], GraphSnapshot).version == 1
    core.epoch = "e2"  # a new epoch at the same version is a change too
    box.periodic(force=True)
    assert len(pubs["snapshot"].puts) == 3 and box.counters.get("snapshots") == 3


def test_the_point_map_goes_out_when_there_are_points_and_the_version_moved() -> None:
    box, core, _, pubs = outbox(snapshot_period_s=0.0)
    core.version, core.voxels = 1, np.ones((4, 3))
    box.periodic()
    assert len(pubs["map"].puts) == 1 and decode(pubs["map"].puts[0][0], PointMap).points.shape == (4, 3)
    box.periodic()
    core.version = 2
    box.periodic()  # within point_map_period_s
    assert len(pubs["map"].puts) == 1
    box.periodic(force=True)
    assert len(pubs["map"].puts) == 2 and box.counters.get("point_maps") == 2


def test_rerun_is_off_unless_configured() -> None:
    box, _, _, _ = outbox()
    box._open_rerun()
    box.rerun()  # nothing configured: nothing logged, nothing raised
    box.close()
    assert box.counters.get("rerun_errors") == 0
    box._rerun = types.SimpleNamespace(log=lambda core: 1 / 0, close=lambda: None)
    box.rerun()  # a failing viewer never stops mapping
    assert box.counters.get("rerun_errors") == 1
