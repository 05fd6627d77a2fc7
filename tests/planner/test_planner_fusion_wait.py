"""The planner chooses a robot's next goal on a graph that includes the robot's arrival frame: it waits for a
graph version whose ``frames`` cover ``RobotState.last_frame_seq`` (a delayed mapper), with a timeout."""

from __future__ import annotations

import numpy as np

from mapper.graph_store import GraphStore
from planner.config import PlannerNodeConfig
from planner.node import PlannerNode
from protocol.codec import decode, encode
from protocol.graph import apply_delta
from protocol.messages import GraphDelta, GraphSnapshot, Intrinsics, RobotState, Viewpoint, ViewpointSet


def _state(status: str, seq: int | None) -> RobotState:
    return RobotState(robot_id="r1", stamp_ns=1, status=status, x=0.0, y=0.0, yaw_rad=0.0,  # type: ignore[arg-type]
                      T_world_cam=np.eye(4).tolist(), last_frame_seq=seq)


def _node(wait_s: float = 5.0) -> PlannerNode:
    node = PlannerNode(PlannerNodeConfig(fusion_wait_s=wait_s))
    node.viewpoints["r1"] = ViewpointSet(robot_id="r1", camera_height_m=1.0, intrinsics=Intrinsics.from_fov(64, 48, 90),
                                         viewpoints=[Viewpoint(vp_id=0, x=1.0, y=0.0, yaw_rad=0.0)])
    return node


def test_no_new_goal_until_the_arrival_frame_is_in_the_graph() -> None:
    node = _node()
    node.graph = GraphSnapshot(version=3, stamp_ns=0, frames={"r1": 8})  # the mapper is behind
    node.states["r1"] = _state("arrived", 10)
    assert node.robots_to_plan(100.0) == {}
    assert node.robots_to_plan(101.0) == {}  # still waiting, counted once
    assert node.counters.get("fusion_waits") == 1
    # the mapper catches up: a delta covering frame 10 (here one that changed nothing else)
    node.graph = apply_delta(node.graph, GraphDelta(version=4, stamp_ns=2, frames={"r1": 10}))
    assert list(node.robots_to_plan(102.0)) == ["r1"]
    assert node.counters.get("fusion_wait_timeouts") == 0


def test_waiting_gives_up_after_the_timeout_and_says_so() -> None:
    node = _node(wait_s=5.0)
    node.states["r1"] = _state("arrived", 11)
    assert node.robots_to_plan(200.0) == {}
    assert node.robots_to_plan(204.0) == {}
    assert list(node.robots_to_plan(205.5)) == ["r1"]
    assert list(node.robots_to_plan(206.0)) == ["r1"]
    assert node.counters.get("fusion_wait_timeouts") == 1


def test_robots_that_do_not_report_frames_are_not_held_back() -> None:
    node = _node()
    node.states["r1"] = _state("arrived", None)  # an older robot agent (schema 1.0)
    assert list(node.robots_to_plan(0.0)) == ["r1"]
    assert list(_node(wait_s=0.0).robots_to_plan(0.0)) == []  # no state yet: nothing to plan
    off = _node(wait_s=0.0)
    off.states["r1"] = _state("arrived", 10)
    assert list(off.robots_to_plan(0.0)) == ["r1"]


def test_the_store_reports_processed_frames_in_deltas_and_snapshots() -> None:
    store = GraphStore()
    assert store.commit_frames({"r1": 4}, 10) == GraphDelta(version=1, stamp_ns=10, frames={"r1": 4})
    assert store.commit_frames({"r1": 4}, 11) is None  # nothing new
    assert store.commit([], [], [], 12, {"r1": 5}) is None  # no change: the frame is not recorded ...
    delta = store.commit_frames({"r1": 5}, 13)  # ... so the frames-only delta still says it
    assert delta is not None and delta.version == 2 and delta.frames == {"r1": 5}
    snap = store.snapshot()
    assert snap.frames == {"r1": 5}
    assert decode(encode(snap), GraphSnapshot).frames == {"r1": 5}


def test_an_older_robot_agent_state_still_decodes() -> None:
    import msgpack

    env = msgpack.unpackb(encode(_state("arrived", 7)), raw=False, strict_map_key=False)
    assert env[3] == 1  # schema 1.1 carries last_frame_seq
    env[3] = 0
    del env[4]["last_frame_seq"]
    old = decode(msgpack.packb(env, use_bin_type=True), RobotState)
    assert old.last_frame_seq is None and old.status == "arrived"


def test_the_mapper_says_a_robot_frame_was_processed_even_when_it_changed_nothing() -> None:
    from bench.explore import core_config
    from mapper.core import MapperCore
    from mapper.geometry.contract import View

    core = MapperCore(core_config("mvs", "classical"))
    blank = View(np.full((48, 64, 3), 90, np.uint8), "r1", Intrinsics.from_fov(64, 48, 90), np.eye(4), seq=3)
    assert core.ingest(blank) is None  # one featureless frame: nothing to map
    delta = core.mark_processed(blank)
    assert delta is not None and delta.frames == {"r1": 3} and not delta.upserted
    assert core.snapshot().frames == {"r1": 3}
    assert core.mark_processed(blank) is None


def test_the_wait_follows_the_mappers_measured_pace() -> None:
    node = _node(wait_s=5.0)
    node.graph = GraphSnapshot(version=3, stamp_ns=0, frames={"r1": 8})
    node.states["r1"] = _state("arrived", 10)
    assert node.robots_to_plan(100.0) == {}
    assert list(node.robots_to_plan(105.5)) == ["r1"]  # the first wait: 5 s, then planned anyway
    node.graph = apply_delta(node.graph, GraphDelta(version=4, stamp_ns=2, frames={"r1": 10}))
    node.states["r1"] = _state("moving", 10)
    node.robots_to_plan(108.0)  # the loaded mapper fused frame 10 8 s after the arrival: measured though late
    assert node.fusion_wait.delays_s[-1] == 8.0
    assert node.counters.get("fusion_wait_limit_s") == 12.0  # 1.5 x 8 s
    node.states["r1"] = _state("arrived", 12)
    assert node.robots_to_plan(120.0) == {}
    assert node.robots_to_plan(129.0) == {}  # 9 s: past the old 5 s, still waiting
    node.graph = apply_delta(node.graph, GraphDelta(version=5, stamp_ns=3, frames={"r1": 12}))
    assert list(node.robots_to_plan(130.0)) == ["r1"]  # planned on a graph with its arrival frame
    assert node.counters.get("fusion_wait_timeouts") == 1
