"""The mapper's snapshot query: encoded once per graph change, never stale."""

from __future__ import annotations

from mapper.config import MapperCoreConfig
from mapper.core import MapperCore
from mapper.queries import GraphQueries
from protocol.codec import decode
from protocol.keys import Keys
from protocol.messages import GraphSnapshot
from protocol.transport import Counters


def test_a_polled_snapshot_is_encoded_once_per_graph_version() -> None:
    core = MapperCore(MapperCoreConfig())
    counters = Counters()
    q = GraphQueries(core, Keys("t"), counters, lambda *_: None)
    first = q.snapshot_bytes()
    assert q.snapshot_bytes() is first and counters.get("snapshot_encodes") == 1
    with core.lock:
        assert core.store.commit_frames({"cam0": 7}, 123) is not None  # a new version
    again = q.snapshot_bytes()
    snap = decode(again, GraphSnapshot)
    assert again != first and snap.version == core.version and snap.frames == {"cam0": 7}
    assert counters.get("snapshot_encodes") == 2
