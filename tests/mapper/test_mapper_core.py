"""MapperCore in-process on ray-cast boxes (oracle geometry and ORACLE 2D perception, no simulator)."""

from __future__ import annotations

import pytest

from mapper.geometry.contract import View
from mapper.persistence import load_state, save_state
from protocol.graph import apply_delta
from protocol.messages import GraphSnapshot
from protocol.query import GraphQuery
from tests.support.boxes import EYES, INTR, oracle_core, view


def test_pipeline_builds_graph_and_deltas_follow() -> None:
    core = oracle_core()
    snap = GraphSnapshot(version=0, stamp_ns=0)
    for i, eye in enumerate(EYES):
        delta = core.ingest(view(eye, i))
        assert delta is not None and delta.version == i + 1
        snap = apply_delta(snap, delta)
    assert snap == core.snapshot()
    labels = sorted(n.label for n in snap.nodes)
    assert labels == ["basket", "chair", "table"]
    by_label = {n.label: n.node_id for n in snap.nodes}
    triples = {(e.subject_id, e.predicate, e.object_id) for e in snap.edges}
    assert (by_label["basket"], "on_top_of", by_label["table"]) in triples
    assert (by_label["chair"], "next_to", by_label["table"]) in triples
    # The same view again is not a keyframe.
    assert core.ingest(view(EYES[-1], 99)) is None
    assert core.counters["views_not_keyframe"] == 1
    pm = core.point_map()
    assert len(pm.points) > 0 and pm.counts is not None and pm.counts.max() >= 2
    assert [n.label for n in core.query(GraphQuery(label="bask"))] == ["basket"]
    assert [n.label for n in core.query(GraphQuery(near=(1.57, 0.32, 0.45), radius=0.3))] == ["chair"]
    assert core.query(GraphQuery(since_version=snap.version)) == []


def test_unposed_view_with_oracle_geometry_still_works() -> None:
    core = oracle_core()
    assert core.ingest(view(EYES[0], 0, posed=False)) is not None
    assert len(core.snapshot().nodes) == 3


def test_view_without_oracle_is_counted_not_raised() -> None:
    core = oracle_core()
    v = view(EYES[0], 0)
    bare = View(image=v.image, source_id="cam9", intrinsics=INTR, T_world_cam=v.T_world_cam, seq=1)
    assert core.ingest(bare) is None
    assert core.counters["keyframe_errors"] == 1
    assert core.ingest(v) is not None


def test_state_round_trip(tmp_path) -> None:
    core = oracle_core()
    for i, eye in enumerate(EYES[:2]):
        core.ingest(view(eye, i))
    save_state(tmp_path, core.state())
    again = oracle_core()
    state = load_state(tmp_path)
    assert state is not None
    again.load_state(state)
    assert again.snapshot() == core.snapshot()
    d1, d2 = core.ingest(view(EYES[2], 2)), again.ingest(view(EYES[2], 2))
    assert d1 == d2 and d1 is not None and d1.version == 3


def test_corrupt_state_is_moved_aside(tmp_path) -> None:
    (tmp_path / "mapper_state.msgpack").write_bytes(b"\x00garbage")
    assert load_state(tmp_path) is None
    assert (tmp_path / "mapper_state.corrupt").exists()
    with pytest.raises(ValueError):
        oracle_core().load_state({"format": 99})


def test_a_deferred_keyframe_stays_kept_after_the_store_lets_it_go() -> None:
    """A keyframe with no stereo partner yet is deferred and retried later; when newer keyframes push it out
    of the bounded store, the mapper must still keep it (a worker job for its retry needs its JPEG)."""
    import numpy as np

    from mapper.config import GeometryConfig, KeyframeConfig, MapperCoreConfig, SingleViewConfig
    from mapper.core import MapperCore
    from protocol.poses import look_at

    core = MapperCore(MapperCoreConfig(geometry=GeometryConfig(backend="mvs"),
                                       keyframes=KeyframeConfig(max_keyframes=2),
                                       single_view=SingleViewConfig(enabled=False)))
    img = np.full((INTR.height, INTR.width, 3), 90, np.uint8)
    lone = View(img, "cam-a", INTR, look_at([0.0, 0.0, 1.0], [0.0, 3.0, 1.0]), seq=0, stamp_ns=1)
    core.ingest(lone)
    assert core.counters["keyframes_deferred"] == 1
    for k in range(3):  # later keyframes of another source fill the store
        core.keyframes.add(View(img, "robot", INTR, look_at([5.0 + k, 0.0, 1.0], [5.0 + k, 3.0, 1.0]), seq=k))
    assert lone.key not in {v.key for v in core.keyframes.views()}
    assert lone.key in {v.key for v in core.views_to_keep()}
