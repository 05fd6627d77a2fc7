"""The robot agent's control logic, without Zenoh: goals in (decoded, judged, answered), the body driven
(with the goal capture and the exploration budget), the state it reports.

:class:`RobotControl` publishes through four hooks (:meth:`~RobotControl.publish_frame`,
:meth:`~RobotControl._publish_state`, :meth:`~RobotControl._publish_viewpoints`,
:meth:`~RobotControl._publish_goal_status`); the process shell :class:`robot_agent.node.RobotAgent` implements
them on its publishers, tests on fakes.
"""

from __future__ import annotations

import collections
import itertools
import logging
import math
import threading
import time

import numpy as np

from protocol.messages import FrameHeader, GoalStatus, NbvGoal, RobotState, RobotStatus, ViewpointSet, rows
from protocol.ratelog import RateLimitedLog
from protocol.transport import Counters, StatusReporter
from robot_agent.bodies import create_body
from robot_agent.bodies.base import Capture, RobotBody
from robot_agent.config import RobotAgentConfig
from robot_agent.goals import (
    Budget,
    GoalMailbox,
    GoalRefused,
    RefusalLimiter,
    capture_waypoints,
    goal_problem,
    parse_goal,
)

log = logging.getLogger("argus.robot_agent")
ACK_QUEUE = 64
"""Refusals decided in Zenoh callbacks wait here (bounded) for the control loop to publish them."""


class RobotControl:
    """One robot's control. ``tick`` is one control step; ``control_loop(stop)`` runs them at ``tick_hz``."""

    def __init__(self, config: RobotAgentConfig, body: RobotBody | None = None) -> None:
        self.config = config
        self.body: RobotBody = body if body is not None else create_body(config.body)
        self.budget = Budget(config.budget.max_distance_m, config.budget.max_steps)
        self.counters = Counters()
        self.bad_input = RateLimitedLog(log)  # bad-input warnings: first per reason, then a summary per period
        self.refusals = RateLimitedLog(log, level=logging.INFO)  # refused goals: a stranger may send thousands
        self.mailbox = GoalMailbox()
        self.viewpoint_set = ViewpointSet(
            robot_id=config.id,
            camera_height_m=self.body.camera_height_m,
            camera_pitch_deg=self.body.camera_pitch_deg,
            intrinsics=self.body.intrinsics,
            max_range_m=self.body.max_range_m,
            viewpoints=self.body.viewpoints(),
        )
        self.status: RobotStatus = "idle"
        self.goal: NbvGoal | None = None
        # goal capture: the legs still to drive and the one being driven, as (x, y, yaw, take a frame there)
        self._legs: list[tuple[float, float, float, bool]] = []
        self._leg: tuple[float, float, float, bool] | None = None
        self.goal_id: str | None = None
        self.reason: str | None = None
        self.steps = 0
        self.viewpoint_id: int | None = None
        self.exhausted: str | None = None
        self.seq = 0
        self._travel_cost: np.ndarray | None = None
        self._reporter: StatusReporter | None = None
        self._received = itertools.count(1)
        self.limiter = RefusalLimiter()
        self._acks: collections.deque[GoalStatus] = collections.deque(maxlen=ACK_QUEUE)
        self._last_frame = self._last_state = self._last_viewpoints = time.monotonic()

    # --- what the shell implements ------------------------------------------------------------
    def publish_frame(self, reliable: bool = False) -> tuple[float, float, float] | None:
        """Capture and publish a frame at the current pose (``reliable``: never dropped); the (capture, encode,
        put) milliseconds, or None when it failed."""
        raise NotImplementedError

    def _publish_state(self) -> None:
        raise NotImplementedError

    def _publish_viewpoints(self) -> None:
        raise NotImplementedError

    def _publish_goal_status(self, status: GoalStatus) -> None:
        raise NotImplementedError

    # --- goals in (Zenoh threads) and their answers ---------------------------------------------
    def on_goal_bytes(self, data: bytes) -> None:
        """Decode a goal payload into the mailbox; garbage is counted, refused (queued answer) and dropped."""
        self.counters.add("goals_received")
        received = next(self._received)
        try:
            goal, form = parse_goal(data, f"{self.config.id}-goal-{received}", time.time_ns())
        except GoalRefused as e:
            self.counters.add("goals_garbage")
            self._queue_refusal(e.goal_id, e.reason, received)  # answered (rate-limited) on goal/status
            self.bad_input.warning("goals_garbage", "refusing an unreadable goal payload (%d bytes): %s",
                                   len(data), e.reason)
            return
        self.counters.add(f"goals_{form}")
        old = self.mailbox.put(goal, received)
        if old is not None:
            self._queue_refusal(old[0].goal_id, f"superseded by goal {goal.goal_id!r} before it was started", old[1])

    def _queue_refusal(self, goal_id: str | None, reason: str, received: int) -> bool:
        """Queue a refusal for the control loop to publish; False when the rate limit only counted it."""
        if not self.limiter.allow(time.monotonic()):
            return False
        if len(self._acks) == self._acks.maxlen:
            self.counters.add("goal_acks_dropped")  # the loop is stalled; the oldest queued answer goes
        self._acks.append(self._goal_status(goal_id, False, reason, received))
        return True

    def _goal_status(self, goal_id: str | None, accepted: bool, reason: str, received: int) -> GoalStatus:
        return GoalStatus(robot_id=self.config.id, stamp_ns=time.time_ns(), goal_id=goal_id, accepted=accepted,
                          reason=reason, received=received)

    def _answer_goal(self, goal: NbvGoal, accepted: bool, reason: str, received: int) -> None:
        """Publish a goal's answer now (control thread); refusals go through the rate limit."""
        if not accepted and not self.limiter.allow(time.monotonic()):
            return
        self._publish_goal_status(self._goal_status(goal.goal_id, accepted, reason, received))

    def _flush_acks(self) -> None:
        while self._acks:
            self._publish_goal_status(self._acks.popleft())

    # --- state ------------------------------------------------------------------------------
    def frame_header(self, cap: Capture, stamp_ns: int, map_always: bool = False) -> FrameHeader:
        """The header of a frame captured now (``seq``: the next one), posed by odometry (never trusted);
        ``map_always``: an arrival or stop frame, which the next goal is planned on."""
        h, w = cap.rgb.shape[:2]
        cov = self.body.pose_covariance()
        intr = self.body.intrinsics
        return FrameHeader(
            source_id=self.config.id,
            source_kind="robot",
            seq=self.seq,
            stamp_ns=stamp_ns,
            width=w,
            height=h,
            intrinsics=intr if (intr.width, intr.height) == (w, h) else intr.scaled(w, h),
            T_world_cam=rows(self.body.T_world_cam_odom()),
            pose_covariance=None if cov is None else rows(cov),
            pose_trusted=False,
            map_always=map_always,
        )

    def _refresh_travel_cost(self) -> None:
        t0 = time.perf_counter()
        self._travel_cost = self.body.travel_costs_m(self.viewpoint_set.viewpoints)
        self.counters.ema("travel_cost_ms", (time.perf_counter() - t0) * 1e3)

    def state(self) -> RobotState:
        x, y, yaw = self.body.pose_odom()
        return RobotState(
            robot_id=self.config.id,
            stamp_ns=time.time_ns(),
            status=self.status,
            x=x,
            y=y,
            yaw_rad=yaw,
            T_world_cam=rows(self.body.T_world_cam_odom()),
            goal_id=self.goal_id,
            reason=self.reason,
            distance_m=self.body.distance_m(),
            steps=self.steps,
            viewpoint_id=self.viewpoint_id,
            travel_cost_m=None if self.status == "moving" else self._travel_cost,
            last_frame_seq=self.seq - 1 if self.seq > 0 else None,
        )

    def _set(self, status: RobotStatus, reason: str | None = None) -> None:
        self.status, self.reason = status, reason
        if status != "moving":
            self._refresh_travel_cost()
        self._publish_state()

    # --- control ----------------------------------------------------------------------------
    def handle_goal(self, goal: NbvGoal, received: int = 0) -> None:
        """Validate and start a goal (pre-empting any current one), or refuse it with a reason; either way
        publish its GoalStatus (``received``: the payload's receipt number)."""
        if self.goal is not None and goal.goal_id == self.goal_id and self.status in ("moving", "arrived"):
            # A planner re-sending the goal in progress (or just reached) must not restart it or
            # count another step; it gets the current state again.
            self.counters.add("goals_duplicate")
            self._answer_goal(goal, True, "", received)
            self._publish_state()
            return
        problem = goal_problem(goal, self.config.id)
        if problem is None and self.exhausted is not None:
            self.body.stop()
            self.goal_id = goal.goal_id
            self.counters.add("goals_refused")
            log.info("refusing goal %s: %s", goal.goal_id, self.exhausted)
            self._answer_goal(goal, False, self.exhausted, received)
            self._set("budget_exhausted", self.exhausted)
            return
        if problem is None:
            problem = self.body.drive_to(goal.x, goal.y, goal.yaw_rad)
        self.goal_id = goal.goal_id
        if problem is not None:
            self.body.stop()
            self.goal = None
            self.counters.add("goals_refused")
            self.refusals.warning("goals_refused", "refusing goal %s: %s", goal.goal_id, problem)
            self._answer_goal(goal, False, problem, received)
            self._set("refused", problem)
            return
        if self.status == "moving":
            self.counters.add("goals_preempted")
        self._legs, self._leg = [], None
        self.goal = goal
        self.viewpoint_id = None
        self.counters.add("goals_accepted")
        log.info("goal %s: driving to (%.2f, %.2f, %.0f deg)", goal.goal_id, goal.x, goal.y,
                 math.degrees(goal.yaw_rad))
        self._answer_goal(goal, True, "", received)
        self._set("moving")

    def _capture_step(self, result: str) -> bool:
        """The goal capture (``frames.goal_capture_m``): on reaching the goal, drive to the poses left and
        right of it, publishing a frame at each, then back to the goal. True while it goes on (the robot
        stays ``moving``); False when the goal is finally reached or failed, or there is no capture."""
        goal, leg = self.goal, self._leg
        if goal is None:
            return False
        if leg is None:  # the goal itself was reached (or failed): start the capture?
            if result != "arrived" or self.config.frames.goal_capture_m <= 0:
                return False
            self._legs = [(*p, True) for p in capture_waypoints(goal.x, goal.y, goal.yaw_rad,
                                                                 self.config.frames.goal_capture_m)]
            self._legs[-1] = (*self._legs[-1][:3], False)  # the way back: no frame, the arrival frame follows
        elif not leg[3]:  # back at the goal after the capture: a normal arrival (or failure) from here
            self._leg = None
            return False
        elif result == "arrived":
            self.publish_frame(reliable=True)
            self.counters.add("capture_frames")
        while self._legs:
            nxt = self._legs.pop(0)
            if self.body.drive_to(*nxt[:3]) is None:
                self._leg = nxt
                return True
            self.counters.add("capture_skipped")  # blocked floor on that side (or no way back): skipped
        self._leg = None
        return False

    def tick(self, dt_wall_s: float) -> None:
        """One control step: take a goal, advance the body, publish what is due."""
        self.bad_input.flush()
        self.refusals.flush()
        self._flush_acks()
        item = self.mailbox.take_with_receipt()
        if item is not None:
            self.handle_goal(*item)
        now = time.monotonic()
        if self.status == "moving":
            result = self.body.step(dt_wall_s * self.config.motion.time_scale)
            driven_out = Budget(self.budget.max_distance_m).exhausted(self.body.distance_m(), 0)
            if result in ("arrived", "failed") and driven_out is None and self._capture_step(result):
                self._publish_state()  # the goal capture goes on: still moving
            elif result == "arrived":
                self.steps += 1
                self.counters.add("arrivals")
                self.viewpoint_id = self.goal.vp_id if self.goal is not None else None
                self.publish_frame(reliable=True)  # always one frame on arrival, before the state says so
                self._set("arrived")
                self.exhausted = self.budget.exhausted(self.body.distance_m(), self.steps)
                if self.exhausted is not None:
                    self._set("budget_exhausted", self.exhausted)
            elif result == "failed":
                self.counters.add("failures")
                self.publish_frame(reliable=True)
                self._set("failed", "the body could not reach the goal")
            elif driven_out is not None:
                self.body.stop()
                self.exhausted = driven_out
                self.publish_frame(reliable=True)
                self._set("budget_exhausted", driven_out)
            else:
                rate = self.config.frames.moving_rate_hz
                if rate > 0 and now - self._last_frame >= 1.0 / rate:
                    self.publish_frame()
                    self._publish_state()
        else:
            idle = self.config.frames.idle_period_s
            if idle > 0 and now - self._last_frame >= idle:
                self.publish_frame()
        if now - self._last_state >= self.config.state_period_s:
            self._publish_state()
        if now - self._last_viewpoints >= self.config.viewpoints_period_s:
            self._publish_viewpoints()

    def control_loop(self, stop: threading.Event) -> None:
        period = 1.0 / self.config.motion.tick_hz
        last = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            dt, last = now - last, now
            try:
                self.tick(dt)
            except Exception as e:  # noqa: BLE001 - a body bug must not take the robot agent down
                self.counters.add("tick_errors")
                if self._reporter is not None:
                    self._reporter.last_error = f"control step failed: {e}"
                log.exception("control step failed")
                self.body.stop()
                if self.status == "moving":
                    self._set("failed", f"control step failed: {e}")
            stop.wait(max(0.0, period - (time.monotonic() - now)))

