from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.keys import Keys, validate_id
from protocol.messages import GraphNode, OrientedBox
from protocol.query import GraphQuery

ids = st.from_regex(r"[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,30}", fullmatch=True)


@given(ids, ids)
def test_frame_keys_round_trip(site: str, source: str) -> None:
    k = Keys(site)
    assert k.parse_frame(k.cam_frame(source)) == ("fixed", source)
    assert k.parse_frame(k.robot_frame(source)) == ("robot", source)
    assert k.parse_frame(k.oracle("robot", source)) == ("robot", source)
    assert k.parse_robot(k.robot_goal(source)) == (source, "goal")
    assert k.parse_robot(k.robot_state(source)) == (source, "state")
    assert k.parse_robot(k.robot_viewpoints(source)) == (source, "viewpoints")
    assert k.parse_node(k.graph_node(source)) == source
    assert k.parse_alive(k.alive("mapper", source)) == ("mapper", source)
    assert k.parse_status(k.status("planner", source)) == ("planner", source)


def test_layout_matches_the_design() -> None:
    k = Keys("lab", prefix="argus")
    assert k.cam_frame("c1") == "argus/lab/cam/c1/frame"
    assert k.robot_goal("r1") == "argus/lab/robot/r1/goal"
    assert k.graph_snapshot == "argus/lab/graph/snapshot"
    assert k.graph_delta == "argus/lab/graph/delta"
    assert k.graph_node("n7") == "argus/lab/graph/node/n7"
    assert k.graph_all == "argus/lab/graph/**"
    assert k.map_points == "argus/lab/map/points"
    assert k.alive("mapper", "m") == "argus/lab/alive/mapper/m"
    assert k.all_frames == "argus/lab/*/*/frame"


@pytest.mark.parametrize("bad", ["", "a/b", "a*", "$x", "a?b", "a#", "..", "a b", "x" * 129, "é"])
def test_bad_ids_are_refused(bad: str) -> None:
    with pytest.raises(ValueError):
        validate_id(bad)
    with pytest.raises(ValueError):
        Keys().cam_frame(bad)


@pytest.mark.parametrize("key", ["argus/default/cam/c1/goal", "argus/other/cam/c1/frame", "argus/default/cam/frame",
                                 "argus/default/graph/node/a/b", "argus/default/alive/x"])
def test_parsers_refuse_foreign_keys(key: str) -> None:
    k = Keys()
    for parse in (k.parse_frame, k.parse_node, k.parse_alive, k.parse_robot):
        with pytest.raises(ValueError):
            parse(key)


def test_graph_query_round_trip_and_matching() -> None:
    q = GraphQuery(label="chair", near=(1.0, 2.0, 0.5), radius=1.5, since_version=3)
    params = q.to_parameters()
    assert params == "label=chair;near=1,2,0.5;radius=1.5;since_version=3"
    assert GraphQuery.from_parameters(params) == q
    node = GraphNode(node_id="n", label="office chair", label_confidence=1, centroid=(1.5, 2.5, 0.5),
                     box=OrientedBox(center=(1.5, 2.5, 0.5), extent=(0.5, 0.5, 1)), point_count=1,
                     observation_count=1, first_seen_ns=0, last_seen_ns=0)
    assert q.matches(node)
    assert not GraphQuery(label="table").matches(node)
    assert not GraphQuery(near=(5, 5, 0), radius=1).matches(node)


@pytest.mark.parametrize("params", ["colour=red", "near=1,2", "radius=x", "near=1,2,nan", "label"])
def test_graph_query_refuses_bad_parameters(params: str) -> None:
    with pytest.raises(ValueError):
        GraphQuery.from_parameters(params)
