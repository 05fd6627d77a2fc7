"""Robot agent test helpers: a planner-like Zenoh peer of one robot, a kinematic robot's config and
start-up, and an in-process agent whose publishers are fakes."""

from __future__ import annotations

import time
from pathlib import Path

from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.messages import NbvGoal, RobotState, ViewpointSet
from robot_agent.config import RobotAgentConfig
from robot_agent.node import RobotAgent
from tests.support.procs import FramePeer, Proc, wait_for

KEYS = Keys("default")
RID = "rob_t"


class RobotClient(FramePeer):
    """A planner-like peer: collects one robot's states, frames and Status; sends goals."""

    def __init__(self, router: str, robot_id: str = RID) -> None:
        super().__init__(router, KEYS.robot_frame(robot_id), KEYS.status("robot-agent", robot_id))
        self.robot_id = robot_id
        self.states: list[RobotState] = []
        self._subs.append(self.session.declare_subscriber(KEYS.robot_state(robot_id), self._on_state))

    def _on_state(self, sample) -> None:  # noqa: ANN001
        msg = decode(sample.payload.to_bytes(), RobotState)
        with self._lock:
            self.states.append(msg)

    def send(self, payload: bytes) -> None:
        self.session.put(KEYS.robot_goal(self.robot_id), payload)

    def goal(self, goal_id: str, x: float, y: float, yaw: float = 0.0, vp_id: int | None = None,
             robot_id: str | None = None) -> None:
        self.send(encode(NbvGoal(goal_id=goal_id, robot_id=robot_id or self.robot_id, stamp_ns=time.time_ns(),
                                 x=x, y=y, yaw_rad=yaw, vp_id=vp_id)))

    def query_viewpoints(self, timeout: float = 5.0) -> ViewpointSet | None:
        for reply in self.session.get(KEYS.robot_viewpoints(self.robot_id), timeout=timeout):
            if reply.ok is not None:
                return decode(reply.ok.payload.to_bytes(), ViewpointSet)
        return None

    def state_where(self, pred) -> RobotState | None:  # noqa: ANN001
        with self._lock:
            return next((s for s in self.states if pred(s)), None)

    def counter(self, name: str) -> float:
        with self._lock:
            return max((s.counters.get(name, 0.0) for s in self.statuses), default=0.0)



def kinematic_config(path: Path, router: str, body_extra: str = "", extra: str = "", capture_m: float = 0.0) -> Path:
    """A kinematic robot's config (goal capture off unless ``capture_m``: these tests time the drive itself)."""
    path.write_text(
        f"""id = "{RID}"
state_period_s = 0.5
viewpoints_period_s = 1.0
status_period_s = 0.2
{extra}
[body]
type = "kinematic"
bounds_m = [0.0, 0.0, 6.0, 4.0]
obstacles = [[2.5, 0.0, 3.5, 2.5]]
start = [1.0, 1.0, 0.0]
speed_mps = 1.0
turn_rate_dps = 180.0
viewpoint_spacing_m = 1.0
odom_trans_sigma = 0.01
odom_yaw_sigma = 0.005
{body_extra}
[frames]
moving_rate_hz = 5.0
goal_capture_m = {capture_m}
[motion]
tick_hz = 50.0
time_scale = 4.0
[zenoh]
mode = "client"
connect = ["{router}"]
"""
    )
    return path


def start_agent(tmp_path: Path, router: str, procs: list[Proc], client_factory, args: tuple[str, ...] = (),
                **kw) -> tuple[Proc, RobotClient]:
    client = client_factory(router)
    proc = Proc(["robot-agent", "--config", str(kinematic_config(tmp_path / "robot.toml", router, **kw)), *args])
    procs.append(proc)
    wait_for(lambda: client.state_where(lambda s: s.status == "idle") is not None, timeout=30,
             what=f"an idle state; output:\n{proc.output}")
    return proc, client


class FakePub:
    def __init__(self) -> None:
        self.puts: list[bytes] = []
        self.attachments: list[bytes | None] = []

    def put(self, payload, attachment=None) -> None:  # noqa: ANN001
        self.puts.append(bytes(payload))
        self.attachments.append(None if attachment is None else bytes(attachment))


class FakeReporter:
    last_error = None


def agent_with_fakes(**cfg) -> RobotAgent:
    config = RobotAgentConfig(id="r", body={"type": "kinematic", "start": [1.0, 1.0, 0.0], "speed_mps": 1.0,
                                            "odom_trans_sigma": 0.0, "odom_yaw_sigma": 0.0}, **cfg)
    agent = RobotAgent(config)
    for name in ("_frame_pub", "_arrival_pub", "_state_pub", "_vp_pub"):
        setattr(agent, name, FakePub())
    agent._oracle_pub = None
    agent._reporter = FakeReporter()
    agent._last_frame = agent._last_state = agent._last_viewpoints = time.monotonic()
    return agent
