"""Robots without a liveliness token expire; robots with one stay (planner inbox, no session)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from planner import synthetic as S
from planner.config import PlannerNodeConfig
from planner.inbox import ROBOT_ROLE, PlannerInbox
from protocol.codec import encode
from protocol.messages import RobotState


@dataclass
class _Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class _Sample:
    key_expr: str
    payload: _Payload
    kind: str = "SampleKind.PUT"


def _state(rid: str) -> RobotState:
    return RobotState(robot_id=rid, stamp_ns=1, status="idle", x=1.0, y=1.0, yaw_rad=0.0,
                      T_world_cam=np.eye(4).tolist())


def test_a_robot_without_a_token_expires_and_one_with_a_token_stays() -> None:
    inbox = PlannerInbox(PlannerNodeConfig(unannounced_expire_s=30.0))
    k = inbox.keys
    vset = S.grid_viewpoints("ghost", (0.6, 0.6), (3.0, 3.0), spacing_m=1.0)
    for rid in ("ghost", "real"):
        inbox.on_state(_Sample(k.robot_state(rid), _Payload(encode(_state(rid)))))
        inbox.on_viewpoints(_Sample(k.robot_viewpoints(rid), _Payload(encode(vset.model_copy(
            update={"robot_id": rid})))))
    inbox.on_alive(_Sample(k.alive(ROBOT_ROLE, "real"), _Payload(b"")))
    assert sorted(inbox.unannounced()) == ["ghost"]
    now = time.monotonic()
    assert inbox.expire_unannounced(now + 10.0) == []  # heard from recently: kept
    assert inbox.expire_unannounced(now + 31.0) == ["ghost"]
    assert set(inbox.states) == {"real"} and "ghost" not in inbox.viewpoints
    assert inbox.counters.get("robots_expired") == 1 and inbox.counters.get("robots_lost") == 0
    # An expired robot that speaks again is taken again (it was not 'gone', only silent).
    inbox.on_state(_Sample(k.robot_state("ghost"), _Payload(encode(_state("ghost")))))
    assert "ghost" in inbox.states
