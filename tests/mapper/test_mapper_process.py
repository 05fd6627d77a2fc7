"""``argus mapper`` as a real process on loopback: deltas, snapshots, queries, bad input, restart.

Frames are published by the test itself (JPEG + header, with ORACLE samples) from a tiny ray-cast
scene, and the mapper runs with oracle geometry and ORACLE 2D perception to stay fast.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
import pytest

from mapper.persistence import load_state
from protocol.codec import decode, encode
from protocol.graph import apply_delta
from protocol.jpeg import encode_jpeg
from protocol.messages import FrameHeader, GraphNode, GraphSnapshot, PointMap
from protocol.query import GraphQuery
from tests.support.boxes import EYES
from tests.support.mapper_peer import Consumer, mapper_args
from tests.support.procs import Proc, wait_for


@pytest.fixture
def consumer(router: str):
    c = Consumer(router)
    yield c
    c.close()


def test_mapper_process_end_to_end(router: str, procs: list[Proc], consumer: Consumer, tmp_path: Path) -> None:
    state_dir = tmp_path / "state"
    mapper = Proc(mapper_args(router, state_dir))
    procs.append(mapper)
    wait_for(lambda: consumer.snapshot() is not None, timeout=60, what=f"mapper answering\n{mapper.output}")
    first = consumer.snapshot()
    assert first is not None and len(first.epoch) == 16  # a new state directory: a new epoch
    assert first == GraphSnapshot(epoch=first.epoch, version=0, stamp_ns=0)

    # Garbage on the frame key: a bad JPEG with a good header, a bad attachment, no attachment.
    keys = consumer.keys
    good = FrameHeader(source_id="robot1", source_kind="robot", seq=500, stamp_ns=1, width=8, height=8)
    consumer.frame_pub.put(b"\xff\xd8not a jpeg\xff\xd9", attachment=encode(good))
    consumer.frame_pub.put(encode_jpeg(np.zeros((8, 8, 3), np.uint8)), attachment=b"\x93garbage")
    consumer.session.put(keys.robot_frame("robot1"), b"no attachment")
    wait_for(lambda: consumer.status.get("decode_errors", 0) >= 1 and consumer.status.get("header_errors", 0) >= 2,
             timeout=20, what=f"bad frames counted: {consumer.status}")
    assert mapper.alive()

    for i, eye in enumerate(EYES):
        consumer.send(eye, i)
        wait_for(lambda i=i: len(consumer.deltas) >= i + 1, timeout=30, what=f"delta {i + 1}\n{mapper.output}")
    versions = [d.version for d in consumer.deltas]
    assert versions == list(range(1, len(EYES) + 1))
    snap = first
    for d in consumer.deltas:
        snap = apply_delta(snap, d)
    served = consumer.snapshot()
    assert served == snap
    assert sorted(n.label for n in snap.nodes) == ["basket", "chair", "table"]
    assert snap.edges

    # Queries match their selectors.
    chair = [n for n in snap.nodes if n.label == "chair"]
    assert consumer.nodes(GraphQuery(label="CHAIR")) == chair
    assert consumer.nodes(GraphQuery(near=chair[0].centroid, radius=0.2)) == chair
    assert consumer.nodes(GraphQuery(id=chair[0].node_id)) == chair
    assert consumer.nodes(GraphQuery(since_version=snap.version)) == []
    assert consumer.nodes(GraphQuery()) == snap.nodes
    node_key = keys.graph_node(chair[0].node_id)
    assert [decode(b, GraphNode) for b in consumer.get(node_key)] == chair
    assert consumer.get(keys.graph_nodes, "bogus=1") == []  # an error reply, not a crash
    # The point map is publish-only on its key, but its newest value answers a late joiner's get.
    wait_for(lambda: consumer.get(keys.map_points), timeout=20, what="the point map answering a get")
    (points,) = consumer.get(keys.map_points)
    assert len(decode(points, PointMap).points) > 0
    assert mapper.alive()

    # Killed without warning and restarted: the same graph (ids) comes back at a version never published
    # (versions are leased ahead of use, see mapper.keeper), in the same epoch.
    wait_for(lambda: (load_state(state_dir) or {}).get("store", {}).get("snapshot") is not None
             and decode(load_state(state_dir)["store"]["snapshot"], GraphSnapshot).version == snap.version,
             timeout=20, what="state saved")
    mapper.signal(signal.SIGKILL)
    mapper.wait(timeout=10)
    again = Proc(mapper_args(router, state_dir))
    procs.append(again)
    t0 = time.monotonic()
    wait_for(lambda: (s := consumer.snapshot()) is not None and s.version > snap.version,
             timeout=60, what=f"restarted mapper\n{again.output}")
    resumed = consumer.snapshot()
    assert resumed is not None and resumed.epoch == snap.epoch
    assert (resumed.nodes, resumed.edges) == (snap.nodes, snap.edges)
    # It carries on from there: the next change is the resumed version + 1, with no id reused.
    consumer.send([0.2, 1.9, 1.5], 100)
    wait_for(lambda: len(consumer.deltas) > len(EYES), timeout=30, what=f"delta after restart\n{again.output}")
    assert consumer.deltas[-1].version == resumed.version + 1
    assert time.monotonic() - t0 < 60
