"""Fault: a robot agent dies while driving. The planner notices through liveliness, plans for the
remaining robot, and takes the dead robot back when it rejoins. Recovery times are printed."""

from __future__ import annotations

import signal
import threading
import time

from planner import synthetic as S
from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.messages import NbvGoal, RobotState, Status
from protocol.session import client, open_session
from tests.support.procs import Proc, wait_for
from tests.support.robot import RID, kinematic_config

KEYS = Keys()


def test_planner_forgets_a_killed_robot_and_takes_it_back(tmp_path, router: str, procs: list[Proc]) -> None:
    goals: dict[str, list[NbvGoal]] = {RID: [], "r2": []}
    status: dict[str, float] = {}
    lock = threading.Lock()

    def on_goal(sample) -> None:  # noqa: ANN001
        g = decode(sample.payload.to_bytes(), NbvGoal)
        with lock:
            goals.setdefault(g.robot_id, []).append(g)

    def on_status(sample) -> None:  # noqa: ANN001
        with lock:
            status.update(decode(sample.payload.to_bytes(), Status).counters)

    moving: list[float] = []

    def on_state(sample) -> None:  # noqa: ANN001
        if decode(sample.payload.to_bytes(), RobotState).status == "moving":
            moving.append(time.monotonic())

    def counter(name: str) -> float:
        with lock:
            return status.get(name, 0.0)

    planner = Proc(["planner", "--connect", router, "--strategy", "see"])
    procs.append(planner)
    w = S.apartment(0)
    with open_session(client(router)) as session, open_session(client(router)) as r2:
        subs = [session.declare_subscriber(KEYS.all_robot_goals, on_goal),
                session.declare_subscriber(KEYS.status("planner", "planner"), on_status),
                session.declare_subscriber(KEYS.robot_state(RID), on_state)]
        wait_for(lambda: counter("decisions") >= 0 and status, timeout=60, what=f"planner status\n{planner.output}")
        pts = w["points"]
        session.put(KEYS.map_points, encode(S.point_map(pts[(pts[:, 0] < 6) & (pts[:, 1] < 5)], 0.05)))
        session.put(KEYS.graph_snapshot, encode(S.snapshot(w["nodes"][:2], version=3)))
        # r2: a robot played by this test, with its own session and liveliness token.
        token = r2.liveliness().declare_token(KEYS.alive("robot-agent", "r2"))
        vset = S.grid_viewpoints("r2", (0.6, 0.6), (5.4, 3.4), spacing_m=1.0)
        r2.put(KEYS.robot_viewpoints("r2"), encode(vset))
        r2.put(KEYS.robot_state("r2"), encode(S.robot_state("r2", 1.0, 1.0, 0.0, "idle")))
        # the real robot agent (kinematic body)
        cfg = kinematic_config(tmp_path / "robot.toml", router)
        robot = Proc(["robot-agent", "--config", str(cfg)])
        procs.append(robot)
        wait_for(lambda: goals[RID] and goals["r2"], timeout=60, what=f"goals for both robots\n{planner.output}")
        wait_for(lambda: counter("robots") == 2, timeout=20, what="planner counts two robots")

        wait_for(lambda: moving, timeout=30, what="the robot driving")
        robot.signal(signal.SIGKILL)  # dies while driving to its goal
        t_kill = time.monotonic()
        wait_for(lambda: counter("robots_lost") >= 1 and counter("robots") == 1, timeout=30,
                 what=f"planner notices the dead robot\n{planner.output}")
        noticed_s = time.monotonic() - t_kill
        n_r2 = len(goals["r2"])
        g = goals["r2"][-1]
        r2.put(KEYS.robot_state("r2"), encode(S.robot_state("r2", g.x, g.y, g.yaw_rad, "arrived", goal_id=g.goal_id)))
        wait_for(lambda: len(goals["r2"]) > n_r2, timeout=30, what="the remaining robot gets its next goal")

        n_rid = len(goals[RID])
        t_back = time.monotonic()
        again = Proc(["robot-agent", "--config", str(cfg)])
        procs.append(again)
        wait_for(lambda: len(goals[RID]) > n_rid and counter("robots") == 2, timeout=60,
                 what=f"the restarted robot is planned for again\n{planner.output}")
        rejoin_s = time.monotonic() - t_back
        print(f"\n[fault robot] planner noticed the killed robot after {noticed_s:.1f} s; "
              f"restarted robot got a goal {rejoin_s:.1f} s after its restart")
        assert planner.alive()
        token.undeclare()
        for s in subs:
            s.undeclare()
