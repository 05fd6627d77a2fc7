"""Integration tests of ``argus robot-agent`` (kinematic body: no simulator, fast)."""

from __future__ import annotations

import math
import signal

import numpy as np
import pytest

from protocol.codec import decode, encode
from protocol.jpeg import decode_jpeg
from protocol.messages import OracleFrame, RobotState, Status
from protocol.transport import Frame
from tests.support.procs import Proc, wait_for
from tests.support.robot import KEYS, RID, RobotClient, start_agent


def wait_arrival_frame(client: RobotClient, arrived: RobotState) -> Frame:
    """The frame taken at the arrival pose (waits for it: it may reach us after the state)."""
    T = np.asarray(arrived.T_world_cam)

    def find() -> Frame | None:
        with client._lock:
            return next((f for f in client.frames if np.allclose(np.asarray(f.header.T_world_cam), T, atol=1e-9)),
                        None)

    wait_for(lambda: find() is not None, timeout=10, what="the arrival frame")
    frame = find()
    assert frame is not None
    return frame


def test_goal_drives_moving_then_arrived_with_arrival_frame(tmp_path, router, procs, client_factory):
    proc, client = start_agent(tmp_path, router, procs, client_factory)
    vps = client.query_viewpoints()
    assert vps is not None and vps.robot_id == RID and len(vps.viewpoints) > 10
    idle = client.state_where(lambda s: s.status == "idle")
    assert idle.travel_cost_m is not None and idle.travel_cost_m.shape == (len(vps.viewpoints),)
    # Viewpoints behind the obstacle cannot be reached in a straight line; pick a far reachable one.
    assert np.isinf(idle.travel_cost_m).any()
    target = next(v for v in vps.viewpoints if 2.5 < idle.travel_cost_m[v.vp_id] < np.inf
                  and abs(v.yaw_rad - math.pi / 2) < 1e-6)
    client.goal("g1", target.x, target.y, target.yaw_rad, vp_id=target.vp_id)
    wait_for(lambda: client.state_where(lambda s: s.status == "arrived" and s.goal_id == "g1") is not None,
             timeout=30, what=f"arrival; states {client.states[-2:]}; output:\n{proc.output}")
    moving = client.state_where(lambda s: s.status == "moving" and s.goal_id == "g1")
    arrived = client.state_where(lambda s: s.status == "arrived" and s.goal_id == "g1")
    assert moving is not None and moving.stamp_ns < arrived.stamp_ns
    assert moving.travel_cost_m is None
    # Odometry noise: 1 cm per sqrt(m) over ~4 m of driving -> a few cm at most.
    assert math.hypot(arrived.x - target.x, arrived.y - target.y) < 0.1
    assert abs(math.remainder(arrived.yaw_rad - target.yaw_rad, 2 * math.pi)) < 0.05
    assert arrived.steps == 1 and arrived.viewpoint_id == target.vp_id
    assert arrived.distance_m == pytest.approx(idle.travel_cost_m[target.vp_id], abs=0.05)
    assert arrived.travel_cost_m[target.vp_id] == pytest.approx(0.0, abs=1e-6)
    # The arrival frame carries the odometry pose at the goal and was sent before the arrival state
    # (sender clock; Zenoh does not order samples across keys at the receiver).
    last = wait_arrival_frame(client, arrived)
    assert last.header.stamp_ns < arrived.stamp_ns
    assert last.header.source_kind == "robot" and last.header.pose_trusted is False
    assert last.header.pose_covariance is not None
    assert last.header.map_always  # the planner plans on it: an overloaded mapper must not shed it
    assert decode_jpeg(last.jpeg).shape == (120, 160, 3)
    assert last.header.seq >= 2  # start frame, frames while moving, arrival frame


def test_bad_goals_refused_garbage_counted_and_agent_carries_on(tmp_path, router, procs, client_factory):
    proc, client = start_agent(tmp_path, router, procs, client_factory)
    client.goal("far", 100.0, 100.0)
    wait_for(lambda: client.state_where(lambda s: s.status == "refused" and s.goal_id == "far") is not None,
             timeout=20, what="refusal of an off-map goal")
    assert "outside" in client.state_where(lambda s: s.goal_id == "far").reason
    client.goal("blocked", 3.0, 3.5 - 1.0)  # inside the obstacle
    wait_for(lambda: client.state_where(lambda s: s.status == "refused" and s.goal_id == "blocked") is not None,
             timeout=20, what="refusal of a goal inside an obstacle")
    client.goal("other", 2.0, 2.0, robot_id="someone_else")
    wait_for(lambda: client.state_where(lambda s: s.goal_id == "other") is not None, timeout=20,
             what="refusal of a goal for another robot")
    assert "addressed to" in client.state_where(lambda s: s.goal_id == "other").reason
    client.goal("nan", float("nan"), 1.0)
    wait_for(lambda: client.state_where(lambda s: s.goal_id == "nan" and s.status == "refused") is not None,
             timeout=20, what="refusal of a NaN goal")
    for junk in (b"", b"\x00garbage", b"\x95\xa4ARG1\xa8nbv_goal\x01\x00\x80", encode(Status(
            role="x", node_id="y", stamp_ns=0))):
        client.send(junk)
    wait_for(lambda: client.counter("goals_garbage") >= 4, timeout=20, what="garbage counted")
    assert proc.alive()
    client.goal("ok", 1.5, 1.5, 0.0)
    wait_for(lambda: client.state_where(lambda s: s.status == "arrived" and s.goal_id == "ok") is not None,
             timeout=20, what="a good goal after the bad ones")


def test_new_goal_preempts_the_current_one(tmp_path, router, procs, client_factory):
    # Real time (1 m/s): the 2.5 m drive to "a" is still under way when "b" arrives.
    proc, client = start_agent(tmp_path, router, procs, client_factory, args=("--time-scale", "1"))
    client.goal("a", 1.0, 3.5, 0.0)
    wait_for(lambda: client.state_where(lambda s: s.status == "moving" and s.goal_id == "a") is not None,
             timeout=20, what="moving to a")
    client.goal("b", 2.0, 1.0, 0.0)
    wait_for(lambda: client.state_where(lambda s: s.status == "arrived" and s.goal_id == "b") is not None,
             timeout=20, what="arrival at b")
    assert client.state_where(lambda s: s.status == "arrived" and s.goal_id == "a") is None
    wait_for(lambda: client.counter("goals_preempted") >= 1, timeout=10, what="goals_preempted counted")


def test_step_budget(tmp_path, router, procs, client_factory):
    proc, client = start_agent(tmp_path, router, procs, client_factory, extra="[budget]\nmax_steps = 1\n")
    client.goal("g1", 1.5, 1.0, 0.0)
    wait_for(lambda: client.state_where(lambda s: s.status == "budget_exhausted") is not None, timeout=20,
             what="budget_exhausted after one step")
    assert client.state_where(lambda s: s.status == "arrived" and s.goal_id == "g1") is not None
    client.goal("g2", 2.0, 1.0, 0.0)
    wait_for(lambda: client.state_where(lambda s: s.goal_id == "g2") is not None, timeout=20, what="g2 answered")
    g2 = client.state_where(lambda s: s.goal_id == "g2")
    assert g2.status == "budget_exhausted" and "budget" in g2.reason
    assert client.state_where(lambda s: s.status == "moving" and s.goal_id == "g2") is None
    proc.signal(signal.SIGTERM)
    assert proc.wait(timeout=15) == 0
    assert "stopped" in proc.output


def test_sim_body_goal_arrives_within_odometry_noise(tmp_path, router, procs, client_factory):
    pytest.importorskip("sim.scene")
    cfg = tmp_path / "sim.toml"
    cfg.write_text(
        f"""id = "{RID}"
state_period_s = 0.5
status_period_s = 0.2
[body]
type = "sim"
family = "furnished_room"
seed = 0
width = 160
height = 120
speed_mps = 1.0
odom_trans_std_per_m = 0.01
odom_rot_std_deg_per_m = 0.5
oracle = true
[frames]
moving_rate_hz = 2.0
goal_capture_m = 0.0
[motion]
tick_hz = 50.0
time_scale = 10.0
[zenoh]
connect = ["{router}"]
"""
    )
    client = client_factory(router)
    oracles: list[OracleFrame] = []
    client._subs.append(client.session.declare_subscriber(
        KEYS.oracle("robot", RID), lambda s: oracles.append(decode(s.payload.to_bytes(), OracleFrame))))
    proc = Proc(["robot-agent", "--config", str(cfg)])
    procs.append(proc)
    wait_for(lambda: client.state_where(lambda s: s.status == "idle") is not None, timeout=60,
             what=f"an idle state; output:\n{proc.output}")
    vps = client.query_viewpoints()
    assert vps is not None and len(vps.viewpoints) > 50 and vps.camera_height_m == 1.0
    idle = client.state_where(lambda s: s.status == "idle")
    cost = idle.travel_cost_m
    assert cost is not None and cost.shape == (len(vps.viewpoints),)
    # The farthest reachable viewpoint: a real geodesic drive of several metres.
    far = int(np.argmax(np.where(np.isfinite(cost), cost, -1)))
    target = vps.viewpoints[far]
    assert cost[far] > 2.0
    client.goal("g1", target.x, target.y, target.yaw_rad, vp_id=target.vp_id)
    wait_for(lambda: client.state_where(lambda s: s.status == "arrived" and s.goal_id == "g1") is not None,
             timeout=60, what=f"arrival; output:\n{proc.output}")
    assert client.state_where(lambda s: s.status == "moving" and s.goal_id == "g1") is not None
    arrived = client.state_where(lambda s: s.status == "arrived")
    # Drift std: 1 cm/sqrt(m) in position plus 0.5 deg/sqrt(m) in heading over the path (< ~8 m):
    # generous 4-sigma bounds.
    d = arrived.distance_m
    # The travel cost is the nav grid's geodesic (8-connected cells); the driven path is string-pulled.
    assert 0.85 * cost[far] <= d <= 1.1 * cost[far]
    pos_sigma = math.sqrt(0.01**2 * d + math.radians(0.5) ** 2 * d**3 / 3)
    assert math.hypot(arrived.x - target.x, arrived.y - target.y) < 4 * pos_sigma + 0.02
    assert abs(math.remainder(arrived.yaw_rad - target.yaw_rad, 2 * math.pi)) < 4 * math.radians(0.5) * math.sqrt(
        d) + 0.02
    last_frame = wait_arrival_frame(client, arrived)
    assert decode_jpeg(last_frame.jpeg).shape == (120, 160, 3)
    assert last_frame.header.pose_covariance is not None
    # The arrival frame's ORACLE sample: same seq, the TRUE pose at the goal (odometry drifted from it).
    wait_for(lambda: any(o.seq == last_frame.header.seq for o in oracles), timeout=10, what="arrival ORACLE")
    truth = next(o for o in oracles if o.seq == last_frame.header.seq)
    T_true = np.asarray(truth.T_world_cam_true)
    assert math.hypot(T_true[0, 3] - target.x, T_true[1, 3] - target.y) < 1e-6
    assert np.linalg.norm(T_true[:3, 3] - np.asarray(last_frame.header.T_world_cam)[:3, 3]) < 4 * pos_sigma + 0.02
    client.goal("out", 50.0, -50.0)
    wait_for(lambda: client.state_where(lambda s: s.goal_id == "out") is not None, timeout=20, what="refusal")
    out = client.state_where(lambda s: s.goal_id == "out")
    assert out.status == "refused" and "free floor" in out.reason
    client.send(b"\xc1\xc1 not msgpack")
    wait_for(lambda: client.counter("goals_garbage") >= 1, timeout=20, what="garbage counted")
    assert proc.alive()


def test_goal_capture_frames_left_and_right_of_the_goal_before_the_arrival(tmp_path, router, procs, client_factory):
    proc, client = start_agent(tmp_path, router, procs, client_factory, capture_m=0.4)
    client.goal("g1", 1.5, 3.0, 0.0)  # facing +x: the sidesteps are along y
    wait_for(lambda: client.state_where(lambda s: s.status == "arrived" and s.goal_id == "g1") is not None,
             timeout=30, what=f"arrival; output:\n{proc.output}")
    arrived = client.state_where(lambda s: s.status == "arrived" and s.goal_id == "g1")
    wait_arrival_frame(client, arrived)
    with client._lock:
        xy = [tuple(np.asarray(f.header.T_world_cam)[:2, 3]) for f in client.frames
              if f.header.stamp_ns <= arrived.stamp_ns]

    def first_near(x: float, y: float) -> int:
        return next(i for i, p in enumerate(xy) if math.hypot(p[0] - x, p[1] - y) < 0.05)

    # a frame 0.4 m left of the goal, then one 0.4 m right of it, then the arrival frame at the goal
    assert first_near(1.5, 3.4) < first_near(1.5, 2.6) < len(xy) - 1
    assert math.hypot(xy[-1][0] - 1.5, xy[-1][1] - 3.0) < 0.05
    assert math.hypot(arrived.x - 1.5, arrived.y - 3.0) < 0.08
    wait_for(lambda: client.counter("capture_frames") == 2, timeout=10, what="the capture counted in status")
