"""When a robot needs a goal (planner/schedule.py): exact cases of goal_due and of the arrival-frame wait."""

from __future__ import annotations

import numpy as np
import pytest

from planner.schedule import FusionWait, Pending, goal_due
from protocol.messages import RobotState

RESEND_S, REPLAN = 5.0, 15


def state(status: str, goal_id: str | None = "g1", seq: int | None = None) -> RobotState:
    return RobotState(robot_id="r1", stamp_ns=1, status=status, x=0.0, y=0.0, yaw_rad=0.0,  # type: ignore[arg-type]
                      T_world_cam=np.eye(4).tolist(), goal_id=goal_id, last_frame_seq=seq)


def due(st: RobotState, pending: Pending | None, n_nodes: int = 10, now_s: float = 100.0) -> str | None:
    return goal_due(st, pending, n_nodes, now_s, RESEND_S, REPLAN)


SENT = Pending("g1", 3, sent_s=98.0, n_nodes=10)  # sent 2 s ago, at 10 nodes


@pytest.mark.parametrize("status", ["arrived", "failed", "refused"])
def test_an_answer_with_no_goal_pending_is_due(status: str) -> None:
    assert due(state(status), None) == "answered"


def test_an_answer_on_our_goal_is_due_and_a_failure_says_so() -> None:
    assert due(state("arrived"), SENT) == "answered"
    assert due(state("failed"), SENT) == "failed"
    assert due(state("refused"), SENT) == "failed"


def test_an_answer_on_another_goal_waits_until_ours_seems_lost() -> None:
    other = state("arrived", goal_id="older")
    assert due(other, SENT, now_s=98.0 + RESEND_S) is None  # not more than resend_s yet
    assert due(other, SENT, now_s=98.0 + RESEND_S + 0.01) == "lost"


def test_idle_is_due_without_a_goal_or_after_resend() -> None:
    assert due(state("idle"), None) == "idle"
    assert due(state("idle"), SENT) is None
    assert due(state("idle"), SENT, now_s=103.5) == "idle"


def test_moving_is_due_only_after_a_large_graph_change() -> None:
    assert due(state("moving"), None, n_nodes=1000) is None
    assert due(state("moving"), SENT, n_nodes=10 + REPLAN - 1) is None
    assert due(state("moving"), SENT, n_nodes=10 + REPLAN) == "graph_change"


def test_budget_exhausted_is_never_due() -> None:
    assert due(state("budget_exhausted"), None) is None


def test_fusion_wait_until_covered_counted_once() -> None:
    w = FusionWait(5.0)
    arrived = state("arrived", seq=10)
    assert w.ready("r1", arrived, 8, 100.0) == (False, "fusion_waits")
    assert w.ready("r1", arrived, 8, 101.0) == (False, None)
    assert w.ready("r1", arrived, 10, 102.0) == (True, None)  # the graph covers frame 10
    assert w.ready("r1", arrived, 8, 103.0) == (False, "fusion_waits")  # a new wait after it was covered


def test_fusion_wait_runs_out_once() -> None:
    w = FusionWait(5.0)
    arrived = state("arrived", seq=10)
    assert w.ready("r1", arrived, -1, 100.0) == (False, "fusion_waits")
    assert w.ready("r1", arrived, -1, 104.9) == (False, None)
    assert w.ready("r1", arrived, -1, 105.5) == (True, "fusion_wait_timeouts")
    assert w.waited_s == pytest.approx(5.5)
    assert w.ready("r1", arrived, -1, 106.0) == (True, None)  # not counted again
    w.forget("r1")
    assert w.ready("r1", arrived, -1, 107.0) == (False, "fusion_waits")


def test_fusion_wait_applies_to_arrivals_with_a_frame_only() -> None:
    assert FusionWait(5.0).ready("r1", state("failed", seq=10), -1, 0.0) == (True, None)
    assert FusionWait(5.0).ready("r1", state("arrived", seq=None), -1, 0.0) == (True, None)
    assert FusionWait(0.0).ready("r1", state("arrived", seq=10), -1, 0.0) == (True, None)


def test_fusion_wait_limit_is_bounded_and_recovers() -> None:
    w = FusionWait(2.0, max_wait_s=10.0, factor=1.5, keep=4)
    assert w.limit_s() == 2.0  # nothing measured yet
    for d in (20.0, 20.0):
        w.delays_s.append(d)
    assert w.limit_s() == 10.0  # never over max_wait_s
    for _ in range(4):  # the mapper is quick again: the old delays leave the window
        w.delays_s.append(0.5)
    assert w.limit_s() == 2.0  # never under wait_s
    assert FusionWait(2.0, max_wait_s=1.0).max_wait_s == 2.0
    assert FusionWait(0.0, max_wait_s=30.0).ready("r1", state("arrived", seq=10), -1, 0.0) == (True, None)
