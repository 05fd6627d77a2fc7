"""The I/O shell of ``argus robot-agent``: goals in; frames, state and viewpoints out.

One control thread owns the body. Zenoh callbacks only decode goals into a one-slot mailbox (the
newest goal wins, so a new goal pre-empts the current one) and answer viewpoint queries from a
cached encoding. Nothing a peer sends can stop the loop: undecodable goals are counted and dropped,
bad goals are refused with a reason in the published state.

Every goal payload gets an answer, a :class:`GoalStatus` on ``robot/<id>/goal/status`` (msgpack envelope)
and ``robot/<id>/goal/status/json`` (JSON): accepted, or refused with the reason (validation error,
wrong robot, budget, superseded in the mailbox, ...). Goals may be ``nbv_goal`` envelopes or plain
JSON objects / msgpack maps (:class:`protocol.messages.PlainGoal`). Refusals are rate-limited
(:class:`robot_agent.goals.RefusalLimiter`); callbacks only queue them (bounded), the control loop publishes.
"""

from __future__ import annotations

import collections
import itertools
import logging
import math
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from protocol.codec import encode
from protocol.jpeg import encode_jpeg
from protocol.keys import Keys
from protocol.messages import (
    FrameHeader,
    GoalStatus,
    NbvGoal,
    OracleFrame,
    RobotState,
    RobotStatus,
    ViewpointSet,
    rows,
)
from protocol.oracle import depth_to_png, ids_to_png
from protocol.ratelog import RateLimitedLog
from protocol.session import open_session_retrying
from protocol.transport import (
    Counters,
    LatestValue,
    StatusReporter,
    declare_frame_publisher,
    declare_message_publisher,
    message_encoding,
    put_frame,
)
from robot_agent.bodies import create_body
from robot_agent.bodies.base import RobotBody
from robot_agent.config import RobotAgentConfig
from robot_agent.goals import Budget, GoalRefused, RefusalLimiter, capture_waypoints, goal_problem, parse_goal

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("argus.robot_agent")
ROLE = "robot-agent"
ACK_QUEUE = 64
"""Refusals decided in Zenoh callbacks wait here (bounded) for the control loop to publish them."""


class GoalMailbox:
    """One slot, newest wins; ``superseded`` counts goals replaced before the loop took them.

    Each goal is held with the receipt number its answer (GoalStatus.received) will carry.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._goal: tuple[NbvGoal, int] | None = None
        self.superseded = 0

    def put(self, goal: NbvGoal, received: int = 0) -> tuple[NbvGoal, int] | None:
        """Hold ``goal``; returns the goal (and receipt number) it replaced, if any."""
        with self._lock:
            old, self._goal = self._goal, (goal, received)
            if old is not None:
                self.superseded += 1
            return old

    def take_with_receipt(self) -> tuple[NbvGoal, int] | None:
        with self._lock:
            item, self._goal = self._goal, None
            return item

    def take(self) -> NbvGoal | None:
        item = self.take_with_receipt()
        return item[0] if item is not None else None


def _ema(counters: Counters, name: str, value: float, alpha: float = 0.2) -> None:
    old = counters.get(name)
    counters.set(name, value if old == 0.0 else (1 - alpha) * old + alpha * value)


class RobotAgent:
    """One robot process. ``run(stop)`` blocks until ``stop`` is set; tests may call it directly."""

    def __init__(self, config: RobotAgentConfig, body: RobotBody | None = None) -> None:
        self.config = config
        self.keys = Keys(config.site, config.key_prefix)
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
        self._viewpoints_bytes = encode(self.viewpoint_set)
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
        self._ack_pubs: list[tuple[Any, bool]] = []  # (publisher, as JSON), set by declare_publishers

    # --- Zenoh callbacks (other threads) -----------------------------------------------------
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

    def _publish_goal_status(self, status: GoalStatus) -> None:
        status = status.model_copy(update={"suppressed": self.limiter.take_suppressed()})
        for pub, as_json in self._ack_pubs:
            try:
                pub.put(status.model_dump_json() if as_json else encode(status))
            except Exception as e:  # noqa: BLE001 - a closing session must not kill the loop
                log.warning("goal status publish failed: %s", e)
        self.counters.add("goal_statuses_sent")

    def _flush_acks(self) -> None:
        while self._acks:
            self._publish_goal_status(self._acks.popleft())

    def _on_goal_sample(self, sample: zenoh.Sample) -> None:
        try:
            self.on_goal_bytes(sample.payload.to_bytes())
        except Exception as e:  # noqa: BLE001 - a callback must never raise into zenoh
            self.counters.add("goals_garbage")
            self.bad_input.warning("goals_garbage", "goal callback failed: %s", e)

    def _on_viewpoints_query(self, query: zenoh.Query) -> None:
        try:
            query.reply(self.keys.robot_viewpoints(self.config.id), self._viewpoints_bytes,
                        encoding=message_encoding(ViewpointSet))
            self.counters.add("viewpoint_queries")
        except Exception as e:  # noqa: BLE001
            log.warning("viewpoint query reply failed: %s", e)

    # --- state ------------------------------------------------------------------------------
    def _refresh_travel_cost(self) -> None:
        t0 = time.perf_counter()
        self._travel_cost = self.body.travel_costs_m(self.viewpoint_set.viewpoints)
        _ema(self.counters, "travel_cost_ms", (time.perf_counter() - t0) * 1e3)

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

    # --- publishing -------------------------------------------------------------------------
    def _publish_state(self) -> None:
        try:
            self._state_pub.put(encode(self.state()))
            self.counters.add("states_sent")
        except Exception as e:  # noqa: BLE001 - a closing session must not kill the loop
            log.warning("state publish failed: %s", e)
        self._last_state = time.monotonic()

    def _publish_viewpoints(self) -> None:
        try:
            self._vp_pub.put(self._viewpoints_bytes)
        except Exception as e:  # noqa: BLE001
            log.warning("viewpoint publish failed: %s", e)
        self._last_viewpoints = time.monotonic()

    def publish_frame(self, reliable: bool = False) -> tuple[float, float, float] | None:
        """Capture at the current pose; publish the ORACLE sample (if enabled) and then the frame.

        ``reliable`` frames (arrival, stop) use the blocking publisher ordered with the state.
        Returns the (capture, encode, put) milliseconds, or None when the frame failed.
        """
        t0 = time.perf_counter()
        try:
            cap = self.body.capture()
            t1 = time.perf_counter()
            jpeg = encode_jpeg(cap.rgb, self.config.frames.jpeg_quality)
            t2 = time.perf_counter()
            h, w = cap.rgb.shape[:2]
            stamp = time.time_ns()
            cov = self.body.pose_covariance()
            intr = self.body.intrinsics
            header = FrameHeader(
                source_id=self.config.id,
                source_kind="robot",
                seq=self.seq,
                stamp_ns=stamp,
                width=w,
                height=h,
                intrinsics=intr if (intr.width, intr.height) == (w, h) else intr.scaled(w, h),
                T_world_cam=rows(self.body.T_world_cam_odom()),
                pose_covariance=None if cov is None else rows(cov),
                pose_trusted=False,
            )
            if cap.oracle is not None and self._oracle_pub is not None:
                o = cap.oracle
                self._oracle_pub.put(encode(OracleFrame(
                    source_id=self.config.id,
                    seq=self.seq,
                    stamp_ns=stamp,
                    T_world_cam_true=rows(o.T_world_cam_true),
                    ids_png=ids_to_png(o.instance_id),
                    depth_png=depth_to_png(o.depth_m),
                    labels={str(k): v for k, v in o.labels.items()},
                )))
            put_frame(self._arrival_pub if reliable else self._frame_pub, header, jpeg)
        except Exception as e:  # noqa: BLE001 - a failed frame is counted, the robot carries on
            self.counters.add("frame_errors")
            if self._reporter is not None:
                self._reporter.last_error = f"frame failed: {e}"
            log.warning("frame failed: %s", e)
            return None
        t3 = time.perf_counter()
        self.seq += 1
        self.counters.add("frames_sent")
        _ema(self.counters, "render_ms", (t1 - t0) * 1e3)
        _ema(self.counters, "encode_ms", (t2 - t1) * 1e3)
        _ema(self.counters, "put_ms", (t3 - t2) * 1e3)
        self._last_frame = time.monotonic()
        return (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3

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

    # --- process ----------------------------------------------------------------------------
    def declare_publishers(self, session: zenoh.Session) -> None:
        """Frame, arrival-frame, ORACLE, state and viewpoint publishers on this robot's keys."""
        import zenoh

        rid = self.config.id
        self._frame_pub = declare_frame_publisher(session, self.keys.robot_frame(rid))
        # Arrival frames must never be dropped: BLOCK, at the state publisher's priority. They are put
        # before the arrival state, so they normally arrive first (receivers get no cross-key order guarantee).
        self._arrival_pub = session.declare_publisher(
            self.keys.robot_frame(rid), encoding=zenoh.Encoding.IMAGE_JPEG,
            congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA,
        )
        self._oracle_pub = (  # sim only; BLOCK so the arrival frame's ORACLE sample is never lost
            session.declare_publisher(
                self.keys.oracle("robot", rid), encoding=message_encoding(OracleFrame),
                congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA,
            )
            if self.body.oracle
            else None
        )
        self._state_pub = LatestValue(session, session.declare_publisher(  # late joiners query the newest state
            self.keys.robot_state(rid), encoding=message_encoding(RobotState),
            congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA,
        ))
        self._vp_pub = declare_message_publisher(
            session, self.keys.robot_viewpoints(rid), important=True, message=ViewpointSet)
        self._ack_pubs = [
            (declare_message_publisher(session, self.keys.robot_goal_status(rid), message=GoalStatus), False),
            (session.declare_publisher(
                self.keys.robot_goal_status_json(rid), encoding=message_encoding(GoalStatus, "application/json"),
                congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.INTERACTIVE_HIGH,
            ), True),
        ]

    def run(self, stop: threading.Event) -> int:
        session = open_session_retrying(self.config.zenoh, stop, log)
        if session is None:
            return 0
        rid = self.config.id
        with session:
            token = session.liveliness().declare_token(self.keys.alive(ROLE, rid))
            self.declare_publishers(session)
            queryable = session.declare_queryable(self.keys.robot_viewpoints(rid), self._on_viewpoints_query)
            goal_sub = session.declare_subscriber(self.keys.robot_goal(rid), self._on_goal_sample)
            self._reporter = StatusReporter(
                session, self.keys.status(ROLE, rid), ROLE, rid, self.counters, self.config.status_period_s,
                extra=lambda: {"goals_superseded": self.mailbox.superseded, "distance_m": self.body.distance_m(),
                               "steps": self.steps, "goal_refusals_suppressed": self.limiter.suppressed_total},
            )
            self._last_frame = self._last_state = self._last_viewpoints = time.monotonic()
            x, y, yaw = self.body.pose_odom()
            log.info("robot %s up at (%.2f, %.2f, %.0f deg) with %d viewpoints; goals on %s", rid, x, y,
                     math.degrees(yaw), len(self.viewpoint_set.viewpoints), self.keys.robot_goal(rid))
            try:
                with self._reporter:
                    self._publish_viewpoints()
                    if self.config.frames.on_start:
                        self.publish_frame(reliable=True)
                    self._set("idle")
                    self._loop(stop)
            finally:
                goal_sub.undeclare()
                queryable.undeclare()
                token.undeclare()
                self.body.close()
                log.info("robot %s stopped (%d steps, %.2f m)", rid, self.steps, self.body.distance_m())
        return 0

    def _loop(self, stop: threading.Event) -> None:
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


def run(config: RobotAgentConfig, stop: threading.Event | None = None) -> int:
    """Run one robot agent until ``stop`` (default: SIGINT/SIGTERM). Raises on configuration errors."""
    from protocol.runtime import install_stop_handlers

    agent = RobotAgent(config)
    stop_event = stop if stop is not None else install_stop_handlers()
    return agent.run(stop_event)
