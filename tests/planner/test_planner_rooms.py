"""The planner with the mapper's room layer: asp's rooms, frontiers and goals by room, a focus room."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner import synthetic as S
from planner.completion import UNEXPLORED, assign_room, room_of_points, rooms_from_layer
from planner.config import AspConfig, PlannerConfig
from planner.core import Planner
from protocol.messages import Viewpoint
from protocol.rooms import RoomEdge, RoomLayer, RoomNode
from tests.planner.test_planner_core import VOXEL, closed_room, two_view_set


def room(rid: str, label: str, x0: float, x1: float, conf: float = 0.9) -> RoomNode:
    return RoomNode(room_id=rid, label=label, label_confidence=conf,
                    polygon=[(x0, -3.0), (x1, -3.0), (x1, 3.0), (x0, 3.0)], floor_z_m=0.0,
                    area_m2=(x1 - x0) * 6.0, observed_fraction=1.0, centroid=((x0 + x1) / 2, 0.0))


LAYER = RoomLayer(version=1, stamp_ns=0, rooms=[room("room1", "kitchen", -3.0, 0.0), room("room2", "unknown", 0.0, 3.0,
                                                                                            conf=0.0)],
                  edges=[RoomEdge(subject_id="room1", predicate="connects", object_id="room2", position=(0.0, 0.0),
                                  width_m=0.9)])


def test_rooms_from_the_layer_and_the_unexplored_rest() -> None:
    vp = np.array([[-1.0, 0.0], [1.0, 1.0], [2.0, -2.0], [7.0, 0.0]])
    rooms = {r.name: r for r in rooms_from_layer(LAYER, vp)}
    assert set(rooms) == {"room1", "room2", UNEXPLORED}
    assert rooms["room1"].kind == "kitchen" and rooms["room2"].kind is None  # unknown: inferred from objects
    assert len(rooms["room1"].vp_xy) == 1 and len(rooms["room2"].vp_xy) == 2 and len(rooms[UNEXPLORED].vp_xy) == 1
    assert room_of_points(np.array([[-0.5, 0.0], [9.0, 9.0]]), LAYER) == ["room1", None]


def test_a_map_room_without_a_viewpoint_still_takes_its_objects() -> None:
    """The demo's planner failed every decision once the mapper's layer had a room no viewpoint lies in (an empty
    minimum): such a room is as near as its outline."""
    rooms = rooms_from_layer(LAYER, np.array([[-1.0, 0.0], [7.0, 0.0]]))
    assert len(next(r for r in rooms if r.name == "room2").vp_xy) == 0
    assert assign_room(np.array([[1.5, 0.5], [-1.0, 0.2], [6.5, 0.0]]), rooms) == ["room2", "room1", UNEXPLORED]


def test_asp_with_the_map_rooms_sees_hypotheses_from_viewpoints_named_by_the_simulator() -> None:
    """Viewpoints carry the simulator's room names, the map's rooms their own ids: asp compared one with the other,
    ruled every hypothesis out of every candidate's room and found no gain (the demo: 30 of 31 decisions fell back
    to frontiers). A candidate's room is the map room it stands in."""
    vps = two_view_set()
    named = vps.model_copy(
        update={"viewpoints": [v.model_copy(update={"room": "living_room"}) for v in vps.viewpoints]})
    robots = {"r1": (S.robot_state("r1", 0.5, 0.5, math.pi / 2), named)}
    pm = S.point_map(closed_room(True), VOXEL, counts=5.0)
    planner = Planner(PlannerConfig(strategy="asp", asp=AspConfig(n_completions=2, n_jitter=1), rooms="map"))
    planner.rooms = LAYER
    goal = planner.plan(S.snapshot([]), pm, robots)[0]
    assert planner.info.room_source == "map" and planner.info.n_hypotheses > 0
    assert goal.reason.startswith("asp: ") and "fallback" not in goal.reason


def test_frontier_and_goal_know_their_room() -> None:
    planner = Planner(PlannerConfig(strategy="see"))
    planner.rooms = LAYER
    pm = S.point_map(closed_room(True), VOXEL, counts=5.0)  # a hole in the x = -3 wall: room1's frontier
    goal = planner.plan(S.snapshot([]), pm, {"r1": (S.robot_state("r1", 0.5, 0.5, math.pi / 2), two_view_set())})[0]
    assert planner.info.frontier_by_room and max(planner.info.frontier_by_room,
                                                 key=planner.info.frontier_by_room.get) == "room1"
    assert goal.reason.endswith("; in room2 (unknown)") or goal.reason.endswith("; in room1 (kitchen)")


def test_asp_uses_the_map_rooms_when_it_has_them() -> None:
    cfg = PlannerConfig(strategy="asp", asp=AspConfig(n_completions=2, n_jitter=1), rooms="auto")
    planner = Planner(cfg)
    pm = S.point_map(closed_room(True), VOXEL, counts=5.0)
    robots = {"r1": (S.robot_state("r1", 0.5, 0.5, math.pi / 2), two_view_set())}
    planner.plan(S.snapshot([]), pm, robots)
    assert planner.info.room_source == "viewpoints"
    planner.rooms = LAYER
    planner.plan(S.snapshot([]), pm, robots)
    assert planner.info.room_source == "map"
    assert set(planner.info.hypotheses_by_room) <= {"room1", "room2", UNEXPLORED, ""}
    planner = Planner(cfg.model_copy(update={"rooms": "viewpoints"}))
    planner.rooms = LAYER
    planner.plan(S.snapshot([]), pm, robots)
    assert planner.info.room_source == "viewpoints"


def test_a_focus_room_keeps_the_goals_inside_it() -> None:
    pm = S.point_map(closed_room(True), VOXEL, counts=5.0)
    vps = [Viewpoint(vp_id=0, x=-1.5, y=0.0, yaw_rad=math.pi), Viewpoint(vp_id=1, x=1.5, y=0.0, yaw_rad=0.0),
           Viewpoint(vp_id=2, x=1.5, y=1.0, yaw_rad=math.pi)]
    vset = two_view_set().model_copy(update={"viewpoints": vps})
    state = S.robot_state("r1", 0.0, 0.0, math.pi / 2)
    for focus, inside in (("room2", {1, 2}), ("kitchen", {0}), ("room1", {0})):
        planner = Planner(PlannerConfig(strategy="see", focus_room=focus))
        planner.rooms = LAYER
        goal = planner.plan(S.snapshot([]), pm, {"r1": (state, vset)})[0]
        assert goal.vp_id in inside, (focus, goal)
    planner = Planner(PlannerConfig(strategy="see", focus_room="bathroom"))  # no such room: no focus
    planner.rooms = LAYER
    assert planner.plan(S.snapshot([]), pm, {"r1": (state, vset)})


def test_hypotheses_in_a_room_narrower_than_the_object() -> None:
    """A map room 0.9 m wide (outline on the 0.1 m grid) and a 2 m object: the proposals go down its middle; the
    lower bound used to round past the upper one ('high - low < 0') and every decision of the demo failed."""
    from planner.hypotheses import _room_props

    lo, hi = np.array([-1.1, -1.1]), np.array([-0.2, -0.2])
    xy, on_floor = _room_props(lo, hi, "floor", 2.0, 0.5, 0.5, 8, np.random.default_rng(0))
    assert on_floor and np.allclose(xy[:, :2], -0.65)


def test_asp_plans_by_frontiers_when_its_completions_fail(monkeypatch: pytest.MonkeyPatch) -> None:
    """A bug in the completion step costs one decision its semantic gain, not the robot its goal."""
    planner = Planner(PlannerConfig(strategy="asp", asp=AspConfig(n_completions=2, n_jitter=1)))

    def broken(*_: object) -> None:
        raise ValueError("high - low < 0")

    monkeypatch.setattr(planner, "_hypotheses", broken)
    pm = S.point_map(closed_room(True), VOXEL, counts=5.0)
    goals = planner.plan(S.snapshot([]), pm, {"r1": (S.robot_state("r1", 0.5, 0.5, math.pi / 2), two_view_set())})
    assert len(goals) == 1 and planner.info.hypotheses_error == "ValueError: high - low < 0"
