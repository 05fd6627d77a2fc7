"""The I/O shell of ``argus planner``: graph, map, robot states and viewpoints in; one goal per robot out.

Zenoh callbacks only decode into bounded holders (newest map, newest state and viewpoint set per
robot, bounded queues of graph snapshots and deltas) and wake the planning thread. That thread follows
the graph with :class:`protocol.graph.GraphFollower` (snapshot + deltas; a new mapper epoch is adopted
at once, a gap or another epoch's delta re-queries the snapshot, and a run of stale snapshots from a
live mapper overrides a forged or lost future version), decides which robots need a goal
(arrived, failed or refused on their goal; idle; or a large graph change while moving), calls the
pure :class:`~planner.core.Planner` and publishes :class:`NbvGoal`\\ s with BLOCK and high priority.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from planner.config import PlannerNodeConfig
from planner.core import Planner
from protocol.codec import DecodeError, M, decode, encode
from protocol.graph import GraphFollower
from protocol.keys import Keys
from protocol.messages import GraphDelta, GraphSnapshot, NbvGoal, PointMap, RobotState, ViewpointSet
from protocol.ratelog import RateLimitedLog
from protocol.session import open_session_retrying
from protocol.transport import Counters, StatusReporter, declare_message_publisher

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("argus.planner")
ROLE = "planner"
MAX_ROBOTS = 64
MAX_PENDING_DELTAS = 256
MAX_PENDING_SNAPSHOTS = 8
TRIGGER_STATES = ("arrived", "failed", "refused")
ROBOT_ROLE = "robot-agent"  # the role in a robot agent's liveliness token


@dataclass
class _Pending:
    goal_id: str
    vp_id: int | None
    sent_s: float
    n_nodes: int


class PlannerNode:
    """One planner process. ``run(stop)`` blocks until ``stop`` is set; tests may call it directly."""

    def __init__(self, config: PlannerNodeConfig, planner: Planner | None = None) -> None:
        self.config = config
        self.keys = Keys(config.site, config.prefix)
        self.planner = planner or Planner(config.planner)
        self.counters = Counters()
        self.bad_input = RateLimitedLog(log)  # bad-input warnings: first per reason, then a summary per period
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self.follower = GraphFollower()
        self._deltas: collections.deque[GraphDelta] = collections.deque(maxlen=MAX_PENDING_DELTAS)
        # Every snapshot counts (stale ones in a row resync the follower), so they queue rather than overwrite.
        self._snapshots: collections.deque[GraphSnapshot] = collections.deque(maxlen=MAX_PENDING_SNAPSHOTS)
        self.point_map: PointMap | None = None
        self.states: dict[str, RobotState] = {}
        # Per robot waiting for its arrival frame to be fused: (that frame's seq, when the wait began).
        self._fusion_wait: dict[str, tuple[int | None, float]] = {}
        self.viewpoints: dict[str, ViewpointSet] = {}
        self.pending: dict[str, _Pending] = {}
        self._gone: set[str] = set()  # robots whose liveliness token went away (until it comes back)
        self._pubs: dict[str, Any] = {}
        self._session: zenoh.Session | None = None

    @property
    def graph(self) -> GraphSnapshot:
        """The graph followed (see :class:`GraphFollower`)."""
        return self.follower.graph

    @graph.setter
    def graph(self, snap: GraphSnapshot) -> None:
        self.follower.graph = snap

    @property
    def _need_snapshot(self) -> bool:
        return self.follower.need_snapshot

    # --- callbacks (Zenoh threads) -----------------------------------------------------------
    def _decode(self, sample: zenoh.Sample, cls: type[M]) -> M | None:
        try:
            return decode(sample.payload.to_bytes(), cls)
        except DecodeError as e:
            self.counters.add("decode_errors")
            self.bad_input.warning("decode_errors", "dropping bad %s on %s: %s", cls.KIND, sample.key_expr, e)
        except Exception as e:  # noqa: BLE001 - a callback must never raise into zenoh
            self.counters.add("decode_errors")
            self.bad_input.warning("decode_errors", "dropping %s on %s: %s", cls.KIND, sample.key_expr, e)
        return None

    def on_snapshot(self, sample: zenoh.Sample) -> None:
        snap = self._decode(sample, GraphSnapshot)
        if snap is not None:
            self.offer_snapshot(snap)

    def offer_snapshot(self, snap: GraphSnapshot) -> None:
        with self._lock:
            if len(self._snapshots) == self._snapshots.maxlen:
                self.counters.add("snapshots_dropped")
            self._snapshots.append(snap)
        self.counters.add("snapshots_in")
        self._wake.set()

    def on_delta(self, sample: zenoh.Sample) -> None:
        delta = self._decode(sample, GraphDelta)
        if delta is None:
            return
        with self._lock:
            if len(self._deltas) == self._deltas.maxlen:
                self.counters.add("deltas_dropped")
                self._deltas.clear()  # the follower sees the gap and re-queries the snapshot
            self._deltas.append(delta)
        self.counters.add("deltas_in")
        self._wake.set()

    def on_map(self, sample: zenoh.Sample) -> None:
        pm = self._decode(sample, PointMap)
        if pm is not None:
            with self._lock:
                self.point_map = pm
            self.counters.add("maps_in")

    def _robot_id(self, sample: zenoh.Sample) -> str | None:
        try:
            return self.keys.parse_robot(str(sample.key_expr))[0]
        except ValueError:
            self.counters.add("bad_keys")
            return None

    def on_state(self, sample: zenoh.Sample) -> None:
        st = self._decode(sample, RobotState)
        rid = self._robot_id(sample)
        if st is None or rid is None:
            return
        if st.robot_id != rid:
            self.counters.add("decode_errors")
            self.bad_input.warning("wrong_robot", "state on %s names robot %r; ignored", sample.key_expr, st.robot_id)
            return
        with self._lock:
            if rid in self._gone:
                self.counters.add("states_of_gone_robots")
                return
            if rid not in self.states and len(self.states) >= MAX_ROBOTS:
                self.counters.add("robots_refused")
                return
            self.states[rid] = st
        self._wake.set()

    def on_viewpoints(self, sample: zenoh.Sample) -> None:
        vps = self._decode(sample, ViewpointSet)
        rid = self._robot_id(sample)
        if vps is None or rid is None:
            return
        if vps.robot_id != rid:
            self.counters.add("decode_errors")
            self.bad_input.warning("wrong_robot", "viewpoints on %s name robot %r; ignored", sample.key_expr,
                                   vps.robot_id)
            return
        with self._lock:
            if rid not in self.viewpoints and len(self.viewpoints) >= MAX_ROBOTS:
                self.counters.add("robots_refused")
                return
            self.viewpoints[rid] = vps
        self._wake.set()

    def on_alive(self, sample: zenoh.Sample) -> None:
        """Robot liveliness: a robot whose token goes away (it stopped, crashed or lost its link) is
        forgotten (state, viewpoints, pending goal, claim), so the others are planned without it; when it
        comes back its state and viewpoints arrive afresh."""
        try:
            role, rid = self.keys.parse_alive(str(sample.key_expr))
        except ValueError:
            self.counters.add("bad_keys")
            return
        if role != ROBOT_ROLE:
            return
        if str(sample.kind).endswith("DELETE"):
            self.forget_robot(rid)
        else:
            with self._lock:
                self._gone.discard(rid)
            self.counters.add("robots_joined")
            log.info("robot %s is alive", rid)

    def forget_robot(self, rid: str) -> None:
        with self._lock:
            if len(self._gone) < MAX_ROBOTS:
                self._gone.add(rid)  # its last samples may still be on their way: ignored until it is back
            known = self.states.pop(rid, None) is not None
            self.viewpoints.pop(rid, None)
            self.pending.pop(rid, None)
            self._fusion_wait.pop(rid, None)
            self.planner.release(rid)
        if known:
            self.counters.add("robots_lost")
            log.warning("robot %s went away (liveliness); planning for the remaining robots", rid)
        self._wake.set()

    # --- planning thread ---------------------------------------------------------------------
    def _follow_graph(self) -> None:
        with self._lock:
            snaps = list(self._snapshots)
            self._snapshots.clear()
            deltas = list(self._deltas)
            self._deltas.clear()
        f = self.follower
        adopted = False
        for snap in snaps:
            held = f.graph.version
            outcome = f.offer_snapshot(snap)
            adopted = adopted or outcome != "stale"
            if outcome == "resynced":
                log.warning("%d snapshots in a row were older than the graph held (v%d): following v%d of epoch %s",
                            f.resync_after, held, f.graph.version, f.graph.epoch or "''")
        for d in sorted(deltas, key=lambda d: d.version):
            if adopted and d.epoch == f.graph.epoch and d.version <= f.graph.version:
                continue  # covered by the snapshot just adopted: not a sign of a stale graph
            if f.offer_delta(d) in ("gap", "other_epoch"):
                break
        for name, value in f.counters.items():
            self.counters.set(name, value)

    def robots_to_plan(self, now_s: float) -> dict[str, tuple[RobotState, ViewpointSet]]:
        """Robots that need a (new) goal now, with their state and viewpoints."""
        out = {}
        n_nodes = len(self.graph.nodes)
        with self._lock:
            items = [(rid, st, self.viewpoints.get(rid)) for rid, st in self.states.items()]
        for rid, st, vps in items:
            if vps is None or not vps.viewpoints or st.status == "budget_exhausted":
                continue
            p = self.pending.get(rid)
            need = False
            if st.status in TRIGGER_STATES:
                if p is None or st.goal_id == p.goal_id:
                    need = True
                    if p is not None and st.status in ("failed", "refused"):
                        self.planner.mark_failed(rid, p.vp_id)
                        self.counters.add("goals_failed")
                else:
                    need = now_s - p.sent_s > self.config.resend_s  # our goal seems lost
            elif st.status == "idle":
                need = p is None or now_s - p.sent_s > self.config.resend_s
            elif st.status == "moving" and p is not None:
                need = n_nodes - p.n_nodes >= self.config.replan_new_nodes
                if need:
                    self.counters.add("replans_graph_change")
            if need and not self._arrival_fused(rid, st, now_s):
                need = False
            if need:
                out[rid] = (st, vps)
        return out

    def _arrival_fused(self, rid: str, st: RobotState, now_s: float) -> bool:
        """Whether the graph covers an arrived robot's arrival frame, or waiting for it has timed out
        (``fusion_wait_s``): the next goal is chosen on a map that includes what the robot just saw."""
        if st.status != "arrived" or st.last_frame_seq is None or self.config.fusion_wait_s <= 0:
            return True
        if self.graph.frames.get(rid, -1) >= st.last_frame_seq:
            self._fusion_wait.pop(rid, None)
            return True
        seq, since = self._fusion_wait.get(rid, (None, now_s))
        if seq != st.last_frame_seq:
            self._fusion_wait[rid] = (st.last_frame_seq, now_s)
            self.counters.add("fusion_waits")
            return False
        if now_s - since < self.config.fusion_wait_s:
            return False
        if since != -math.inf:  # the first time this wait runs out
            self._fusion_wait[rid] = (seq, -math.inf)
            self.counters.add("fusion_wait_timeouts")
            log.warning("robot %s: no graph version covers its arrival frame %d after %.1f s; planning anyway",
                        rid, st.last_frame_seq, now_s - since)
        return True

    def plan_once(self, now_s: float | None = None) -> list:
        """Follow the graph, plan for the robots that need it, publish; returns the goals sent."""
        now_s = time.monotonic() if now_s is None else now_s
        self._follow_graph()
        robots = self.robots_to_plan(now_s)
        if not robots:
            return []
        with self._lock:
            pm = self.point_map
        try:
            goals = self.planner.plan(self.graph, pm, robots)
        except Exception as e:  # noqa: BLE001 - a planning bug must not take the planner down
            self.counters.add("plan_errors")
            log.exception("planning failed")
            self._reporter_error(f"planning failed: {e}")
            for rid in robots:  # back off instead of retrying in a tight loop
                self.pending[rid] = _Pending("", None, now_s, len(self.graph.nodes))
            return []
        info = self.planner.info
        self.counters.add("decisions")
        self.counters.set("decision_ms_last", info.decision_s * 1e3)
        self.counters.set("decision_ms_max", max(self.counters.get("decision_ms_max"), info.decision_s * 1e3))
        self.counters.set("graph_version", self.graph.version)
        self.counters.set("frontier_points", info.n_frontier)
        self.counters.set("hypotheses", info.n_hypotheses)
        if info.sampler_fallback:
            self.counters.add("sampler_fallbacks")
        sent = []
        for g in goals:
            p = self.pending.get(g.robot_id)
            st = robots[g.robot_id][0]
            if st.status == "moving" and p is not None and p.vp_id == g.vp_id:
                p.n_nodes = len(self.graph.nodes)  # same goal after the graph change: keep going
                continue
            self._publish_goal(g)
            self.pending[g.robot_id] = _Pending(g.goal_id, g.vp_id, now_s, len(self.graph.nodes))
            self.counters.set("gain_last", g.expected_gain)
            sent.append(g)
        for rid in robots:
            if rid not in {g.robot_id for g in goals}:
                self.pending[rid] = _Pending(
                    "", None, now_s, len(self.graph.nodes)
                )  # nothing to do: back off
        return sent

    def _reporter_error(self, msg: str) -> None:
        rep = getattr(self, "_reporter", None)
        if rep is not None:
            rep.last_error = msg

    def _publish_goal(self, goal: Any) -> None:
        pub = self._pubs.get(goal.robot_id)
        if pub is None and self._session is not None:
            pub = self._pubs[goal.robot_id] = declare_message_publisher(
                self._session, self.keys.robot_goal(goal.robot_id), important=True, message=NbvGoal
            )
        if pub is None:
            return
        try:
            pub.put(encode(goal))
            self.counters.add("goals_sent")
            log.info(
                "goal %s -> (%.2f, %.2f) gain %.2f: %s (%.0f ms)",
                goal.goal_id,
                goal.x,
                goal.y,
                goal.expected_gain,
                goal.reason,
                self.planner.info.decision_s * 1e3,
            )
        except Exception as e:  # noqa: BLE001 - a closing session must not kill the loop
            self.counters.add("publish_errors")
            log.warning("goal publish failed: %s", e)

    # --- start-up queries --------------------------------------------------------------------
    def _query(self, session: zenoh.Session, key: str, cls: type[M]) -> list[M]:
        import zenoh

        out: list[M] = []
        try:
            # No reply consolidation: the default keeps one reply per key, so a late peer answering
            # with garbage could hide the mapper's snapshot; every reply is judged here instead.
            replies = session.get(key, timeout=self.config.query_timeout_s,
                                  consolidation=zenoh.ConsolidationMode.NONE)
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    out.append(decode(reply.ok.payload.to_bytes(), cls))
                except DecodeError as e:
                    self.counters.add("decode_errors")
                    self.bad_input.warning("bad_replies", "bad %s reply: %s", cls.KIND, e)
        except Exception as e:  # noqa: BLE001 - nobody answering is normal at start-up
            log.debug("query %s failed: %s", key, e)
        return out

    def _initial_queries(self, session: zenoh.Session) -> None:
        self.counters.add("snapshot_queries")
        for snap in self._query(session, self.keys.graph_snapshot, GraphSnapshot):
            self.offer_snapshot(snap)
        for vps in self._query(session, self.keys.all_robot_viewpoints, ViewpointSet):
            with self._lock:
                if len(self.viewpoints) < MAX_ROBOTS:
                    self.viewpoints.setdefault(vps.robot_id, vps)
        self._wake.set()

    # --- process -----------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> int:
        session = open_session_retrying(self.config.zenoh, stop, log)
        if session is None:
            return 0
        k = self.keys
        with session:
            self._session = session
            subs = [
                session.declare_subscriber(k.graph_snapshot, self.on_snapshot),
                session.declare_subscriber(k.graph_delta, self.on_delta),
                session.declare_subscriber(k.map_points, self.on_map),
                session.declare_subscriber(k.all_robot_states, self.on_state),
                session.declare_subscriber(k.all_robot_viewpoints, self.on_viewpoints),
                session.liveliness().declare_subscriber(k.all_alive_of(ROBOT_ROLE), self.on_alive),
            ]
            self._reporter = StatusReporter(
                session,
                k.status(ROLE, self.config.node_id),
                ROLE,
                self.config.node_id,
                self.counters,
                self.config.status_period_s,
                extra=lambda: {"robots": len(self.states), "graph_nodes": len(self.graph.nodes),
                               "graph_version": self.graph.version},
            )
            log.info(
                "planner %s up: strategy %s, sampler %s",
                self.config.node_id,
                self.config.planner.strategy,
                self.config.planner.sampler.kind,
            )
            try:
                with self._reporter:
                    self._initial_queries(session)
                    token = session.liveliness().declare_token(k.alive(ROLE, self.config.node_id))
                    try:
                        self._loop(stop, session)
                    finally:
                        token.undeclare()
            finally:
                for s in subs:
                    s.undeclare()
                self._session = None
        log.info("planner stopped (%d goals sent)", int(self.counters.get("goals_sent")))
        return 0

    def _loop(self, stop: threading.Event, session: zenoh.Session) -> None:
        last_query = time.monotonic()
        while not stop.is_set():
            self._wake.wait(0.25)
            self._wake.clear()
            self.bad_input.flush()
            if self._need_snapshot and time.monotonic() - last_query > 2.0:
                last_query = time.monotonic()
                self.counters.add("snapshot_queries")
                for snap in self._query(session, self.keys.graph_snapshot, GraphSnapshot):
                    self.offer_snapshot(snap)
                self._follow_graph()
            try:
                self.plan_once()
            except Exception as e:  # noqa: BLE001 - the loop must survive anything
                self.counters.add("loop_errors")
                log.exception("planner loop step failed")
                self._reporter_error(str(e))


def run(config: PlannerNodeConfig, stop: threading.Event | None = None) -> int:
    """Run the planner until ``stop`` (default: SIGINT/SIGTERM)."""
    from protocol.runtime import install_stop_handlers

    node = PlannerNode(config)
    return node.run(stop if stop is not None else install_stop_handlers())
