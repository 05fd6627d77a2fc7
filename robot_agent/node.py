"""The I/O shell of ``argus robot-agent``: goals in; frames, state and viewpoints out.

One control thread owns the body (:class:`robot_agent.control.RobotControl`). Zenoh callbacks only decode
goals into a one-slot mailbox (the newest goal wins, so a new goal pre-empts the current one) and answer
viewpoint queries from a cached encoding. Nothing a peer sends can stop the loop: undecodable goals are
counted and dropped, bad goals are refused with a reason in the published state.

Every goal payload gets an answer, a :class:`GoalStatus` on ``robot/<id>/goal/status`` (msgpack envelope)
and ``robot/<id>/goal/status/json`` (JSON): accepted, or refused with the reason (validation error,
wrong robot, budget, superseded in the mailbox, ...). Goals may be ``nbv_goal`` envelopes or plain
JSON objects / msgpack maps (:class:`protocol.messages.PlainGoal`). Refusals are rate-limited
(:class:`robot_agent.goals.RefusalLimiter`); callbacks only queue them (bounded), the control loop publishes.
"""

from __future__ import annotations

import math
import threading
import time
from typing import TYPE_CHECKING, Any

from protocol.codec import encode
from protocol.jpeg import encode_jpeg
from protocol.keys import Keys
from protocol.messages import GoalStatus, OracleFrame, RobotState, ViewpointSet
from protocol.node import Node, Process
from protocol.transport import message_encoding, put_frame
from robot_agent.bodies.base import RobotBody
from robot_agent.config import RobotAgentConfig
from robot_agent.control import RobotControl, log

if TYPE_CHECKING:
    import zenoh

ROLE = "robot-agent"


class RobotAgent(RobotControl, Process):
    """One robot process. ``run(stop)`` blocks until ``stop`` is set; tests may call it directly."""

    def __init__(self, config: RobotAgentConfig, body: RobotBody | None = None) -> None:
        super().__init__(config, body)
        self.keys = Keys(config.site, config.key_prefix)
        self._viewpoints_bytes = encode(self.viewpoint_set)
        self._ack_pubs: list[tuple[Any, bool]] = []  # (publisher, as JSON), set by declare_publishers
        self.node = Node(config.zenoh, self.keys, ROLE, config.id, counters=self.counters,
                         status_period_s=config.status_period_s, logger=log)

    # --- Zenoh callbacks (other threads) -----------------------------------------------------
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

    # --- publishing (the control's hooks) ---------------------------------------------------
    def _publish_goal_status(self, status: GoalStatus) -> None:
        status = status.model_copy(update={"suppressed": self.limiter.take_suppressed()})
        for pub, as_json in self._ack_pubs:
            self._put(pub, status.model_dump_json() if as_json else encode(status), "goal status")
        self.counters.add("goal_statuses_sent")

    def _publish_state(self) -> None:
        if self._put(self._state_pub, encode(self.state()), "state"):
            self.counters.add("states_sent")
        self._last_state = time.monotonic()

    def _publish_viewpoints(self) -> None:
        self._put(self._vp_pub, self._viewpoints_bytes, "viewpoint")
        self._last_viewpoints = time.monotonic()

    def _put(self, pub: Any, payload: bytes | str, what: str) -> bool:
        try:
            pub.put(payload)
            return True
        except Exception as e:  # noqa: BLE001 - a closing session must not kill the loop
            log.warning("%s publish failed: %s", what, e)
            return False

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
            header = self.frame_header(cap, time.time_ns(), map_always=reliable)
            if cap.oracle is not None and self._oracle_pub is not None:
                self._oracle_pub.put(encode(cap.oracle.message(self.config.id, self.seq, header.stamp_ns)))
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
        times = (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3
        for name, ms in zip(("render_ms", "encode_ms", "put_ms"), times, strict=True):
            self.counters.ema(name, ms)
        self._last_frame = time.monotonic()
        return times

    # --- process ----------------------------------------------------------------------------
    def declare_publishers(self, node: Node) -> None:
        """Frame, arrival-frame, ORACLE, state, viewpoint and goal-status publishers on this robot's keys."""
        rid, k = self.config.id, self.keys
        self._frame_pub = node.frame_publisher(k.robot_frame(rid))
        # Arrival frames must never be dropped: BLOCK, at the state publisher's priority. They are put
        # before the arrival state, so they normally arrive first (receivers get no cross-key order guarantee).
        self._arrival_pub = node.frame_publisher(k.robot_frame(rid), block=True)
        # sim only; BLOCK so the arrival frame's ORACLE sample is never lost
        self._oracle_pub = (node.publisher(k.oracle("robot", rid), message=OracleFrame, important=False, block=True)
                            if self.body.oracle else None)
        # late joiners query the newest state
        self._state_pub = node.latest(node.publisher(k.robot_state(rid), message=RobotState, important=False,
                                                     block=True))
        self._vp_pub = node.publisher(k.robot_viewpoints(rid), message=ViewpointSet)
        self._ack_pubs = [(node.publisher(k.robot_goal_status(rid), message=GoalStatus), False),
                          (node.publisher(k.robot_goal_status_json(rid), message=GoalStatus,
                                          mime="application/json"), True)]

    def serve(self, node: Node) -> None:
        rid = self.config.id
        node.alive()
        self.declare_publishers(node)
        node.queryable(self.keys.robot_viewpoints(rid), self._on_viewpoints_query)
        node.subscribe(self.keys.robot_goal(rid), self._on_goal_sample)
        node.on_exit(self._stopped)
        self._reporter = node.status(extra=lambda: {
            "goals_superseded": self.mailbox.superseded, "distance_m": self.body.distance_m(),
            "steps": self.steps, "goal_refusals_suppressed": self.limiter.suppressed_total})
        self._last_frame = self._last_state = self._last_viewpoints = time.monotonic()
        x, y, yaw = self.body.pose_odom()
        log.info("robot %s up at (%.2f, %.2f, %.0f deg) with %d viewpoints; goals on %s", rid, x, y,
                 math.degrees(yaw), len(self.viewpoint_set.viewpoints), self.keys.robot_goal(rid))
        self._publish_viewpoints()
        if self.config.frames.on_start:
            self.publish_frame(reliable=True)
        self._set("idle")
        self.control_loop(node.stop)

    def _stopped(self) -> None:
        self.body.close()
        log.info("robot %s stopped (%d steps, %.2f m)", self.config.id, self.steps, self.body.distance_m())


def run(config: RobotAgentConfig, stop: threading.Event | None = None) -> int:
    """Run one robot agent until ``stop`` (default: SIGINT/SIGTERM). Raises on configuration errors."""
    return RobotAgent(config).run(stop)
