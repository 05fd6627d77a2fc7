"""When a robot needs a new goal (pure: no I/O, no clock of its own; times are passed in)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from protocol.messages import RobotState

TRIGGER_STATES = ("arrived", "failed", "refused")
Due = Literal["answered", "failed", "lost", "idle", "graph_change"]


@dataclass
class Pending:
    """The goal last sent to a robot (``goal_id`` empty: none, the planner backs off until ``sent_s`` + resend)."""

    goal_id: str
    vp_id: int | None
    sent_s: float
    n_nodes: int


def goal_due(st: RobotState, pending: Pending | None, n_nodes: int, now_s: float, resend_s: float,
             replan_new_nodes: int) -> Due | None:
    """Why the robot in state ``st`` needs a goal now, or None.

    ``answered``: it arrived, failed or was refused on the goal pending (or on none of ours); ``failed``: the
    same, and that goal of ours failed or was refused (its viewpoint is to be marked); ``lost``: it reports
    another goal and ours was sent more than ``resend_s`` ago; ``idle``: idle with no goal pending, or one sent
    more than ``resend_s`` ago; ``graph_change``: moving while ``replan_new_nodes`` nodes were added since.
    """
    if st.status in TRIGGER_STATES:
        if pending is None:
            return "answered"
        if st.goal_id == pending.goal_id:
            return "failed" if st.status in ("failed", "refused") else "answered"
        return "lost" if now_s - pending.sent_s > resend_s else None
    if st.status == "idle":
        return "idle" if pending is None or now_s - pending.sent_s > resend_s else None
    if st.status == "moving" and pending is not None and n_nodes - pending.n_nodes >= replan_new_nodes:
        return "graph_change"
    return None


class FusionWait:
    """Per robot, the wait for a graph version that covers its arrival frame (``wait_s``; 0: never wait), so the
    next goal is chosen on a map that includes what the robot just saw."""

    def __init__(self, wait_s: float) -> None:
        self.wait_s = wait_s
        self._since: dict[str, tuple[int | None, float]] = {}  # robot -> (arrival frame seq, when the wait began)
        self.waited_s = 0.0  # how long the last wait that ran out lasted

    def ready(self, rid: str, st: RobotState, fused_seq: int, now_s: float) -> tuple[bool, str | None]:
        """Whether robot ``rid`` may be planned now (``fused_seq``: its newest frame in the graph, -1 for none),
        with the event to count: ``fusion_waits`` (a wait began), ``fusion_wait_timeouts`` (it ran out) or None."""
        if st.status != "arrived" or st.last_frame_seq is None or self.wait_s <= 0:
            return True, None
        if fused_seq >= st.last_frame_seq:
            self._since.pop(rid, None)
            return True, None
        seq, since = self._since.get(rid, (None, now_s))
        if seq != st.last_frame_seq:
            self._since[rid] = (st.last_frame_seq, now_s)
            return False, "fusion_waits"
        if now_s - since < self.wait_s:
            return False, None
        if since == -math.inf:  # this wait ran out before: planned, not counted again
            return True, None
        self._since[rid] = (seq, -math.inf)
        self.waited_s = now_s - since
        return True, "fusion_wait_timeouts"

    def forget(self, rid: str) -> None:
        self._since.pop(rid, None)
