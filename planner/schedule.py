"""When a robot needs a new goal (pure: no I/O, no clock of its own; times are passed in)."""

from __future__ import annotations

import collections
from dataclasses import dataclass
from typing import Literal

import numpy as np

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
    """Per robot, the wait for a graph version that covers its arrival frame, so the next goal is chosen on a map
    that includes what the robot just saw.

    The wait follows the mapper's measured pace: each arrival that had to wait gives a delay (arrival to the graph
    covering its frame, also when it came after the wait ran out: :meth:`note` sees it), and a wait lasts
    ``factor`` x the 90th percentile of the last ``keep`` delays, never under ``wait_s`` nor over ``max_wait_s``.
    A loaded mapper that takes 8 s per keyframe is waited for; a quick one still gets ``wait_s``. ``wait_s`` 0:
    never wait. Only arrivals that had to wait are measured (a frame already in the graph has no delay to see), so
    the estimate leans long."""

    def __init__(self, wait_s: float, max_wait_s: float | None = None, factor: float = 1.5, keep: int = 16) -> None:
        self.wait_s = wait_s
        self.max_wait_s = wait_s if max_wait_s is None else max(wait_s, max_wait_s)
        self.factor = factor
        self.delays_s: collections.deque[float] = collections.deque(maxlen=max(1, keep))
        # robot -> (arrival frame seq, when the wait began, whether it ran out)
        self._since: dict[str, tuple[int, float, bool]] = {}
        self.waited_s = 0.0  # how long the last wait that ran out lasted

    def limit_s(self) -> float:
        """How long a wait lasts now."""
        if not self.delays_s:
            return self.wait_s
        p90 = float(np.percentile(np.asarray(self.delays_s, np.float64), 90))
        return min(self.max_wait_s, max(self.wait_s, self.factor * p90))

    def _covered(self, rid: str, seq: int, now_s: float) -> None:
        entry = self._since.pop(rid, None)
        if entry is not None and entry[0] == seq:
            self.delays_s.append(max(0.0, now_s - entry[1]))

    def note(self, fused: dict[str, int], now_s: float) -> None:
        """The graph's newest frame per source (``fused``) at ``now_s``: every wait it covers, run out or not,
        gives its delay."""
        for rid, (seq, _, _) in list(self._since.items()):
            if fused.get(rid, -1) >= seq:
                self._covered(rid, seq, now_s)

    def ready(self, rid: str, st: RobotState, fused_seq: int, now_s: float) -> tuple[bool, str | None]:
        """Whether robot ``rid`` may be planned now (``fused_seq``: its newest frame in the graph, -1 for none),
        with the event to count: ``fusion_waits`` (a wait began), ``fusion_wait_timeouts`` (it ran out) or None."""
        if st.status != "arrived" or st.last_frame_seq is None or self.wait_s <= 0:
            return True, None
        if fused_seq >= st.last_frame_seq:
            self._covered(rid, st.last_frame_seq, now_s)
            return True, None
        entry = self._since.get(rid)
        if entry is None or entry[0] != st.last_frame_seq:
            self._since[rid] = (st.last_frame_seq, now_s, False)
            return False, "fusion_waits"
        seq, since, ran_out = entry
        if ran_out:  # this wait ran out before: planned, not counted again
            return True, None
        if now_s - since < self.limit_s():
            return False, None
        self._since[rid] = (seq, since, True)  # kept: the delay is still measured when the frame is fused
        self.waited_s = now_s - since
        return True, "fusion_wait_timeouts"

    def forget(self, rid: str) -> None:
        self._since.pop(rid, None)
