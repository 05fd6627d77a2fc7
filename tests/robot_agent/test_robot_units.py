"""Unit tests of the robot agent's pure parts and the kinematic body (no Zenoh, no simulator)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.codec import encode
from protocol.messages import NbvGoal, Status
from protocol.poses import camera_pose_from_base
from robot_agent.bodies import BODIES, create_body, parse_body_config
from robot_agent.bodies.base import BodyConfigError, RobotBody
from robot_agent.goals import Budget, GoalMailbox, goal_problem
from tests.support.robot import agent_with_fakes


def goal(**kw) -> NbvGoal:
    base = dict(goal_id="g", robot_id="r", stamp_ns=0, x=1.0, y=1.0, yaw_rad=0.0)
    base.update(kw)
    return NbvGoal(**base)


class TestGoalProblem:
    def test_good_goal(self):
        assert goal_problem(goal(), "r") is None

    @pytest.mark.parametrize(
        ("kw", "match"),
        [({"robot_id": "other"}, "addressed to"), ({"x": math.nan}, "non-finite"),
         ({"yaw_rad": math.inf}, "non-finite"), ({"y": 1e9}, "far away")],
    )
    def test_bad_goals(self, kw, match):
        assert match in goal_problem(goal(**kw), "r")


def test_budget():
    assert Budget().exhausted(1e9, 10**6) is None
    assert Budget(max_distance_m=5).exhausted(4.9, 100) is None
    assert "distance" in Budget(max_distance_m=5).exhausted(5.0, 0)
    assert "step" in Budget(max_steps=3).exhausted(0.0, 3)


def test_mailbox_newest_wins():
    box = GoalMailbox()
    assert box.take() is None
    box.put(goal(goal_id="a"))
    box.put(goal(goal_id="b"))
    assert box.take().goal_id == "b" and box.superseded == 1 and box.take() is None


def kinematic(**kw) -> RobotBody:
    cfg = {"type": "kinematic", "start": [1.0, 1.0, 0.0], "speed_mps": 1.0, "turn_rate_dps": 90.0, **kw}
    body = create_body(parse_body_config(cfg))
    assert isinstance(body, RobotBody)
    return body


class TestKinematicBody:
    def test_noise_free_drive_is_exact_and_timed(self):
        body = kinematic(odom_trans_sigma=0.0, odom_yaw_sigma=0.0)
        assert body.drive_to(4.0, 1.0, math.pi / 2) is None
        statuses = [body.step(0.5) for _ in range(8)]
        # 3 m at 1 m/s = 6 steps of 0.5 s, then a 90 deg turn at 90 deg/s = 2 more.
        assert statuses[:7] == ["moving"] * 7 and statuses[7] == "arrived"
        assert body.step(0.5) == "idle"
        assert body.pose_odom() == pytest.approx((4.0, 1.0, math.pi / 2))
        assert body.distance_m() == pytest.approx(3.0)
        assert np.allclose(body.T_world_cam_odom(), camera_pose_from_base(4.0, 1.0, math.pi / 2, 1.0, -15.0))

    def test_odometry_drifts_with_distance_and_covariance_grows(self):
        body = kinematic(odom_trans_sigma=0.05, seed=3)
        cov0 = body.pose_covariance()
        body.drive_to(5.0, 3.0, 0.0)
        while body.step(0.1) == "moving":
            pass
        x, y, _ = body.pose_odom()
        err = math.hypot(x - 5.0, y - 3.0)
        assert 0.0 < err < 5 * 0.05 * math.sqrt(body.distance_m())
        assert body.pose_covariance()[0, 0] > cov0[0, 0]

    def test_refusals_and_stop(self):
        body = kinematic(obstacles=[[2.5, 0.0, 3.5, 2.5]])
        assert "outside" in body.drive_to(10.0, 1.0, 0.0)
        assert "outside" in body.drive_to(3.0, 1.0, 0.0)  # inside the obstacle
        assert "no straight path" in body.drive_to(5.0, 1.0, 0.0)
        assert "finite" in body.drive_to(math.nan, 1.0, 0.0)
        assert body.drive_to(1.0, 3.0, 0.0) is None
        body.step(0.3)
        body.stop()
        assert body.step(1.0) == "idle"

    def test_viewpoints_and_costs(self):
        body = kinematic(obstacles=[[2.5, 0.0, 3.5, 2.5]])
        vps = body.viewpoints()
        assert vps and all(body.is_free(v.x, v.y) for v in vps)
        assert [v.vp_id for v in vps] == list(range(len(vps)))
        cost = body.travel_costs_m(vps)
        assert cost.shape == (len(vps),) and np.isinf(cost).any() and (cost[np.isfinite(cost)] >= 0).all()

    def test_capture_depends_on_pose(self):
        body = kinematic(width=64, height=48)
        a = body.capture().rgb
        body.drive_to(1.0, 1.0, math.pi)
        while body.step(0.5) == "moving":
            pass
        b = body.capture().rgb
        assert a.shape == (48, 64, 3) and a.dtype == np.uint8 and not np.array_equal(a, b)

    def test_bad_config(self):
        with pytest.raises(BodyConfigError, match="not in free space"):
            kinematic(start=[-1.0, 0.0, 0.0])
        with pytest.raises(ValueError, match="xmin < xmax"):
            parse_body_config({"type": "kinematic", "bounds_m": [1, 0, 0, 1]})
        with pytest.raises(BodyConfigError, match="unknown body type"):
            parse_body_config({"type": "hovercraft"})
        assert set(BODIES) >= {"sim", "kinematic"}


def test_agent_tick_drives_publishes_arrival_frame_then_state_and_counts_garbage():
    agent = agent_with_fakes()
    agent.on_goal_bytes(b"junk")
    agent.on_goal_bytes(encode(Status(role="x", node_id="y", stamp_ns=0)))
    assert agent.counters.get("goals_garbage") == 2
    agent.on_goal_bytes(encode(goal(robot_id="r", x=2.0, y=1.0, vp_id=7)))
    agent.tick(0.0)
    assert agent.status == "moving"
    for _ in range(100):
        agent.tick(0.1)
        if agent.status != "moving":
            break
    assert agent.status == "arrived" and agent.steps == 1 and agent.viewpoint_id == 7
    # the default goal capture: a frame 0.3 m left and right of the goal, then the arrival frame at the goal
    assert len(agent._arrival_pub.puts) == 3 and agent.counters.get("capture_frames") == 2
    assert agent.state().travel_cost_m is not None
    x, y, yaw = agent.body.pose_odom()
    assert (x, y) == pytest.approx((2.0, 1.0), abs=0.02)
    assert agent.body.distance_m() == pytest.approx(1.0 + 0.3 + 0.6 + 0.3, abs=0.05)  # sidesteps counted


def test_goal_capture_off_and_blocked_sides() -> None:
    agent = agent_with_fakes(frames={"goal_capture_m": 0.0})
    agent.handle_goal(goal(robot_id="r", x=2.0, y=1.0))
    for _ in range(100):
        agent.tick(0.1)
        if agent.status != "moving":
            break
    assert agent.status == "arrived" and len(agent._arrival_pub.puts) == 1
    assert agent.body.distance_m() == pytest.approx(1.0, abs=0.02)
    # a goal by the room's edge (bounds 0..6 x 0..4 m): the side outside is skipped, the other captured
    agent = agent_with_fakes()
    agent.handle_goal(goal(robot_id="r", x=2.0, y=0.4, yaw_rad=0.0))  # right side (y 0.1) is off the floor
    for _ in range(200):
        agent.tick(0.1)
        if agent.status != "moving":
            break
    assert agent.status == "arrived"
    assert agent.counters.get("capture_frames") == 1 and agent.counters.get("capture_skipped") == 1


def test_a_new_goal_during_the_capture_preempts_it() -> None:
    agent = agent_with_fakes()
    agent.handle_goal(goal(robot_id="r", x=2.0, y=1.0, goal_id="g1"))
    while agent.counters.get("capture_frames") < 1:
        agent.tick(0.05)
    agent.handle_goal(goal(robot_id="r", x=1.0, y=1.5, goal_id="g2"))
    for _ in range(200):
        agent.tick(0.1)
        if agent.status != "moving":
            break
    assert agent.status == "arrived" and agent.goal_id == "g2"
    assert agent.counters.get("capture_frames") == 3  # one of g1, two of g2


def test_agent_distance_budget_stops_the_robot():
    agent = agent_with_fakes(budget={"max_distance_m": 1.0})
    agent.handle_goal(goal(robot_id="r", x=4.0, y=1.0))
    for _ in range(100):
        agent.tick(0.1)
        if agent.status != "moving":
            break
    assert agent.status == "budget_exhausted" and "distance" in agent.reason
    assert agent.body.distance_m() == pytest.approx(1.0, abs=0.11)
    agent.handle_goal(goal(robot_id="r", goal_id="later", x=1.0, y=1.0))
    assert agent.status == "budget_exhausted" and agent.goal_id == "later"


def test_agent_ignores_a_resent_goal_in_progress_or_reached():
    agent = agent_with_fakes()
    g = goal(robot_id="r", goal_id="same", x=2.0, y=1.0)
    agent.handle_goal(g)
    agent.tick(0.1)
    agent.handle_goal(g)  # re-sent while moving: no restart
    for _ in range(100):
        agent.tick(0.1)
        if agent.status != "moving":
            break
    assert agent.status == "arrived" and agent.steps == 1
    agent.handle_goal(g)  # re-sent after arrival: no extra step
    agent.tick(0.1)
    assert agent.status == "arrived" and agent.steps == 1
    assert agent.counters.get("goals_duplicate") == 2
    agent.handle_goal(goal(robot_id="r", goal_id="next", x=1.0, y=1.0))
    assert agent.status == "moving"


@pytest.mark.parametrize("depth_m", [1.0, 2.0, 4.0])
def test_goal_capture_frames_are_sources_the_view_selection_takes(depth_m: float) -> None:
    """The default capture's frames pass the mapper's view-selection thresholds for the arrival frame at
    indoor depths (triangulation angle, overlap, rotation), and both are chosen (distinct directions)."""
    from mapper.geometry.viewselect import Candidate, select_sources
    from protocol.codec import decode
    from protocol.messages import FrameHeader

    agent = agent_with_fakes()
    agent.handle_goal(goal(robot_id="r", x=3.0, y=2.0, yaw_rad=0.5))
    for _ in range(200):
        agent.tick(0.1)
        if agent.status != "moving":
            break
    headers = [decode(a, FrameHeader) for a in agent._arrival_pub.attachments if a is not None]
    assert agent.status == "arrived" and len(headers) == 3
    *capture, arrival = headers
    cands = [Candidate(i, np.asarray(h.T_world_cam), h.intrinsics) for i, h in enumerate(capture)]
    chosen = select_sources(np.asarray(arrival.T_world_cam), arrival.intrinsics, depth_m, cands, k=2)
    assert sorted(s.index for s in chosen) == [0, 1]
    assert all(s.baseline_m == pytest.approx(0.3, abs=0.02) for s in chosen)
