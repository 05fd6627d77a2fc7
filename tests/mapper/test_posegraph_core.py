"""The pose graph's hook in MapperCore: corrected priors, stored keyframes and fused nodes follow a loop."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mapper.posegraph import lift, se2
from tests.support.boxes import EYES, oracle_core, view


def core_with_loops():  # type: ignore[no-untyped-def]
    core = oracle_core()
    core.config.pose_graph = core.config.pose_graph.model_copy(update={"enabled": True})
    from mapper.posegraph import LoopCloser

    core.loops = LoopCloser(core.config.pose_graph)
    return core


def test_without_loops_the_graph_is_unchanged() -> None:
    plain, looped = oracle_core(), core_with_loops()
    for i, eye in enumerate(EYES):
        plain.ingest(view(eye, i))
        looped.ingest(view(eye, i))
    a = {n.node_id: n.centroid for n in plain.nodes()}
    b = {n.node_id: n.centroid for n in looped.nodes()}
    assert a == b
    assert len(looped.loops.graphs["robot1"].keys) == len(EYES)  # type: ignore[union-attr]


def test_calibrated_and_independent_priors_are_not_corrected() -> None:
    core = core_with_loops()
    core.ingest(view(EYES[0], 0))
    core.loops.graphs["robot1"].est[-1] = np.array([5.0, 5.0, 1.0])  # type: ignore[union-attr]  # a big correction
    v = view(EYES[1], 1)
    assert not np.allclose(core._corrected(v).T_world_cam, v.T_world_cam)
    for other in (dataclasses.replace(v, pose_trusted=True), dataclasses.replace(v, prior_rel_rot_deg=math.inf),
                  dataclasses.replace(v, source_id="camera9")):
        assert core._corrected(other) is other


def test_a_loop_moves_stored_keyframes_and_their_nodes() -> None:
    core = core_with_loops()
    for i, eye in enumerate(EYES[:3]):
        core.ingest(view(eye, i))
    before = {n.node_id: np.array(n.centroid) for n in core.nodes()}
    shift = lift(se2(np.array([0.3, 0.0, 0.0])))
    moved_keys = {("robot1", 0), ("robot1", 1), ("robot1", 2)}
    assert core.loops is not None
    core.loops.keyframe = lambda *a, **k: {key: shift for key in moved_keys}  # type: ignore[method-assign]
    delta = core.ingest(view(EYES[3], 3))
    assert delta is not None
    after = {n.node_id: np.array(n.centroid) for n in core.nodes()}
    assert core.counters["keyframes_moved_by_loops"] == 3
    assert core.counters["nodes_moved_by_loops"] >= 1
    moved = [k for k in before if k in after and abs(after[k][0] - before[k][0] - 0.3) < 0.02]
    assert moved, (before, after)
    assert {n.node_id for n in delta.upserted} >= set(moved)  # the moved nodes are re-sent
    stored = {v.key: v for v in core.keyframes.views()}
    assert stored[("robot1", 0)].T_world_cam[0, 3] == pytest.approx(EYES[0][0] + 0.3)


def test_a_failing_pose_graph_is_counted_and_the_keyframe_goes_on() -> None:
    core = core_with_loops()
    assert core.loops is not None

    def broken(*a, **k):  # type: ignore[no-untyped-def]
        raise ValueError("boom")

    core.loops.keyframe = broken  # type: ignore[method-assign]
    delta = core.ingest(view(EYES[0], 0))
    assert delta is not None and len(delta.upserted) > 0
    assert core.counters["pose_graph_errors"] == 1


def test_the_same_keyframe_twice_is_one_graph_node() -> None:
    core = core_with_loops()
    core.ingest(view(EYES[0], 0))
    core.ingest(view(EYES[0], 0), force_keyframe=True)
    assert core.loops is not None and core.loops.graphs["robot1"].keys == [("robot1", 0)]
