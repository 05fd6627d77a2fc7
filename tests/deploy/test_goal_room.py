"""``argus goal --room``: which room a name picks and where the robot is sent to look around it."""

from __future__ import annotations

import math

import pytest

from deploy.goal import main, pick_room, room_goal_xy
from protocol.messages import Intrinsics, Viewpoint, ViewpointSet
from protocol.rooms import RoomLayer, RoomNode


def room(rid: str, label: str, conf: float, x0: float, x1: float) -> RoomNode:
    return RoomNode(room_id=rid, label=label, label_confidence=conf, polygon=[(x0, 0), (x1, 0), (x1, 4), (x0, 4)],
                    floor_z_m=0.0, area_m2=(x1 - x0) * 4, observed_fraction=1.0, centroid=((x0 + x1) / 2, 2.0))


LAYER = RoomLayer(version=1, stamp_ns=0, rooms=[
    room("room1", "kitchen", 0.6, 0, 4), room("room2", "kitchen", 0.9, 4, 8), room("room3", "bedroom", 0.8, 8, 12)])


def test_a_name_is_an_id_or_the_most_confident_room_with_that_label() -> None:
    assert pick_room(LAYER, "room1").room_id == "room1"  # type: ignore[union-attr]
    assert pick_room(LAYER, "kitchen").room_id == "room2"  # type: ignore[union-attr]
    assert pick_room(LAYER, "bathroom") is None


def test_the_goal_is_the_viewpoint_inside_nearest_the_centre_facing_it() -> None:
    vps = ViewpointSet(robot_id="r", camera_height_m=1.0, intrinsics=Intrinsics.from_fov(64, 48, 90.0), viewpoints=[
        Viewpoint(vp_id=0, x=1.0, y=1.0, yaw_rad=0.0), Viewpoint(vp_id=1, x=5.0, y=1.0, yaw_rad=0.0),
        Viewpoint(vp_id=2, x=7.5, y=3.5, yaw_rad=0.0)])
    x, y, yaw = room_goal_xy(LAYER.rooms[1], vps)
    assert (x, y) == (5.0, 1.0) and yaw == pytest.approx(math.atan2(1.0, 1.0))
    assert room_goal_xy(LAYER.rooms[2], vps) == (10.0, 2.0, 0.0)  # no viewpoint inside: its centre
    assert room_goal_xy(LAYER.rooms[0], None) == (2.0, 2.0, 0.0)


def test_either_a_position_or_a_room(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--robot", "r"]) == 2
    assert main(["--robot", "r", "--x", "1", "--y", "2", "--room", "kitchen"]) == 2
    assert "either --x and --y, or --room" in capsys.readouterr().err
